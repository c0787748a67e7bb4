"""Results at an fsspec URL (adarl.runtime.run_folder.results) and the live progress board, without training anything.

The URL tests use ``fakes3://`` (the ``fake_s3`` fixture of conftest.py): a local folder that behaves like an object
store (a move is a copy then a delete, no append, no hard links; every write is logged), so that no code can lean on
local paths or atomic renames.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import pytest

from adarl.errors import AdaRLValueError
from adarl.experiments.execute import _record_attempt, read_attempts, run_is_finished
from adarl.experiments.progress import LiveBoard, ProgressBoard, read_progress, use_live
from adarl.experiments.spec import PlannedRun
from adarl.runtime.run_folder.results import LATEST, RunMirror, filesystem, read_text, scratch_folder


def _ckpt(folder: Path, frames: int, payload: bytes = b"weights", rb: bool = True) -> None:
    d = folder / "checkpoints"
    d.mkdir(parents=True, exist_ok=True)
    if rb:
        (d / f"rb-{frames:012d}" / "storage").mkdir(parents=True)
        (d / f"rb-{frames:012d}" / "storage" / "obs.memmap").write_bytes(b"rb%d" % frames)
    (d / f"ckpt-{frames:012d}.pt").write_bytes(payload + b"%d" % frames)


def _run_folder(folder: Path, total: int = 600) -> None:
    (folder / "metrics" / "scalars").mkdir(parents=True)
    (folder / "recipe.yaml").write_text(f"name: t\nseed: 0\ncollector:\n  total_frames: {total}\n")
    (folder / "metrics" / "scalars" / "train.updates.csv").write_text("50,10\n100,60\n")
    (folder / "metrics" / "scalars" / "train.episode_return.csv").write_text("100,12.5\n")
    _ckpt(folder, 50)


def _remote_files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def test_unknown_protocol_and_missing_backend_name_what_to_do():
    with pytest.raises(AdaRLValueError, match=r"unknown protocol 'nosuch'.*s3, gs"):
        filesystem("nosuch://bucket/exp")
    import importlib.util

    if importlib.util.find_spec("s3fs") is None:
        with pytest.raises(AdaRLValueError, match=r"needs a package that is not installed: pip install s3fs"):
            filesystem("s3://bucket/exp")


def test_cli_rejects_an_unknown_protocol_before_running_anything(tmp_path, capsys):
    from adarl.cli import main

    spec = tmp_path / "s.yaml"
    spec.write_text("kind: experiment\nname: s\nrecipe: quickstart\n")
    assert main(["experiment", str(spec), "-o", "nosuch://b/exp", "--no-live"]) == 2
    assert "unknown protocol 'nosuch'" in capsys.readouterr().err


def test_push_uploads_checkpoint_then_latest_and_prunes(tmp_path, fake_s3):
    local, root = tmp_path / "scratch" / "run", tmp_path / "bucket" / "exp" / "run"
    _run_folder(local)
    mirror = RunMirror(local, f"fakes3://{root}")
    mirror.push()
    assert json.loads((root / "checkpoints" / LATEST).read_text())["frames"] == 50
    # the checkpoint went up under a temporary name and was moved into place before LATEST named it
    ckpt, latest = str(root / "checkpoints" / "ckpt-000000000050.pt"), str(root / "checkpoints" / LATEST)
    order = [p for op, p in fake_s3.writes if op == "mv"]
    assert order.index(ckpt) < order.index(latest)
    assert not any(p == ckpt for op, p in fake_s3.writes if op == "put")
    rb_put = max(i for i, (op, p) in enumerate(fake_s3.writes) if "rb-000000000050" in p)
    assert rb_put < fake_s3.writes.index(("mv", ckpt))
    # a newer checkpoint replaces it at the URL; the local rotation may have removed the older one already
    _ckpt(local, 100)
    (local / "checkpoints" / "ckpt-000000000050.pt").unlink()
    with (local / "metrics" / "scalars" / "train.updates.csv").open("a") as fh:
        fh.write("150,1")  # a row being appended: not uploaded until whole
    assert mirror.has_new_checkpoint()
    mirror.push()
    assert not mirror.has_new_checkpoint()
    files = _remote_files(root)
    assert [f for f in files if f.startswith("checkpoints/")] == [
        "checkpoints/LATEST",
        "checkpoints/ckpt-000000000100.pt",
        "checkpoints/rb-000000000100/storage/obs.memmap",
    ]
    assert not any(".part-" in f or f.endswith(".tmp") for f in files)
    assert (root / "metrics" / "scalars" / "train.updates.csv").read_text() == "50,10\n100,60\n"
    assert "summary.json" not in files
    with (local / "metrics" / "scalars" / "train.updates.csv").open("a") as fh:
        fh.write("0\n")
    (local / "summary.json").write_text(json.dumps({"frames": 600}))
    mirror.push()
    assert not (root / "summary.json").exists()  # only the final push sends it
    assert (root / "metrics" / "scalars" / "train.updates.csv").read_text().endswith("150,10\n")
    fake_s3.writes.clear()
    mirror.push(final=True)
    assert fake_s3.writes[-1] == ("mv", str(root / "summary.json"))  # last: a finished run at the URL is complete
    assert run_is_finished(f"fakes3://{root}")


def test_retry_on_a_fresh_scratch_downloads_the_latest_checkpoint(tmp_path, fake_s3):
    url = f"fakes3://{tmp_path}/bucket/exp/run"
    first = tmp_path / "a" / "run"
    _run_folder(first)
    _ckpt(first, 100)
    RunMirror(first, url).push()
    fresh = RunMirror(tmp_path / "b" / "run", url)
    assert fresh.prepare() == "resume"
    assert [f for f, _ in fresh.local_checkpoints()] == [100]  # LATEST's only
    got = sorted(p.relative_to(fresh.local).as_posix() for p in fresh.local.rglob("*") if p.is_file())
    assert got == sorted(
        p.relative_to(first).as_posix() for p in first.rglob("*") if p.is_file() and "000000000050" not in p.as_posix()
    )
    assert (fresh.local / "checkpoints" / "rb-000000000100" / "storage" / "obs.memmap").read_bytes() == b"rb100"
    fake_s3.writes.clear()
    fresh.push()
    assert fake_s3.writes == []  # what was downloaded is not uploaded again
    # a scratch folder that is ahead of the URL (its last upload was cut off) is kept as is
    _ckpt(fresh.local, 150)
    assert fresh.prepare() == "resume" and fresh.local_checkpoints()[-1][0] == 150
    # a scratch folder behind the URL is replaced by the URL's state
    behind = tmp_path / "c" / "run"
    _run_folder(behind)
    assert RunMirror(behind, url).prepare() == "resume"
    assert [f for f, _ in RunMirror(behind, url).local_checkpoints()] == [100]


def test_a_download_cut_short_leaves_no_checkpoint_behind(tmp_path, fake_s3, monkeypatch):
    url = f"fakes3://{tmp_path}/bucket/run"
    first = tmp_path / "a" / "run"
    _run_folder(first)
    RunMirror(first, url).push()
    get_file = fake_s3.get_file

    def lost_midway(self, rpath, lpath, *args, **kwargs):
        if "rb-" in rpath:  # the checkpoint itself sorts (and arrives) before its buffer
            raise ConnectionError("connection reset")
        return get_file(self, rpath, lpath, *args, **kwargs)

    monkeypatch.setattr(fake_s3, "get_file", lost_midway)
    retry = RunMirror(tmp_path / "b" / "run", url)
    with pytest.raises(ConnectionError):
        retry.prepare()
    assert retry.local_checkpoints() == []
    monkeypatch.setattr(fake_s3, "get_file", get_file)
    assert retry.prepare() == "resume" and [f for f, _ in retry.local_checkpoints()] == [50]
    assert (retry.local / "checkpoints" / "rb-000000000050" / "storage" / "obs.memmap").is_file()


def test_no_checkpoint_at_the_url_means_a_fresh_start(tmp_path, fake_s3):
    url_root = tmp_path / "bucket" / "run"
    (url_root / "metrics").mkdir(parents=True)
    (url_root / "recipe.yaml").write_text("x: 1\n")  # uploaded before the first checkpoint
    local = tmp_path / "s" / "run"
    _run_folder(local)  # a stale scratch folder of an earlier experiment at the same place
    mirror = RunMirror(local, f"fakes3://{url_root}")
    assert mirror.prepare() == "fresh"
    assert not local.exists() and not url_root.exists()


def test_scratch_folder_is_per_experiment_url(tmp_path):
    a = scratch_folder("s3://b/exp1/run", "run", str(tmp_path))
    b = scratch_folder("s3://b/exp2/run", "run", str(tmp_path))
    assert a.name == b.name == "run" and a.parent != b.parent and a.parent.parent == tmp_path
    assert scratch_folder("s3://b/exp1/run", "run", None).parent.parent.name == "adarl-scratch"


def test_attempts_and_progress_read_through_the_url(tmp_path, fake_s3):
    out = f"fakes3://{tmp_path}/bucket/exp"
    run = PlannedRun("algo=a__seed=0", {"algo": "a"}, 0, "quickstart", [], f"{out}/algo=a__seed=0")
    _record_attempt(run, event="start", action="ran")
    _record_attempt(run, event="end", action="ran", status="finished")
    assert [e["event"] for e in read_attempts(out, run.run_id)] == ["start", "end"]
    assert read_attempts(out, "other") == []
    local = tmp_path / "scratch" / run.run_id
    _run_folder(local)
    RunMirror(local, run.path).push()
    prog = read_progress(run.run_id, run.path, "running")
    assert (prog.frames, prog.total_frames, prog.last_return) == (100, 600, 12.5)
    assert read_text(f"{out}/nothing-here") is None


def _board(tmp_path: Path, n: int = 3) -> ProgressBoard:
    runs = []
    for i in range(n):
        folder = tmp_path / f"algo=a__seed={i}"
        _run_folder(folder)
        runs.append(PlannedRun(folder.name, {"algo": "a"}, i, "quickstart", [], str(folder)))
    runs[0].status = "finished"
    board = ProgressBoard(runs)
    board.running = {runs[1].run_id}
    return board


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def test_plain_lines_are_unchanged(tmp_path):
    lines = _board(tmp_path).render()
    assert lines[0] == f"  {'finished':<16} {'algo=a__seed=0':<40} frames 100{'/600':<8} return {'12.5':<8} eta -"
    assert lines[1].split()[0] == "running" and lines[2].split()[0] == "pending"
    assert lines[-1] == "[#############.................] 1/3 runs done, 44% of frames"


def test_live_board_draws_one_row_per_run_and_the_bar(tmp_path):
    from rich.console import Console

    buf = io.StringIO()
    console = Console(file=buf, force_terminal=True, width=120, height=40, color_system="standard")
    board = _board(tmp_path)
    with LiveBoard(board, console=console) as live:
        live.log("[finished] algo=a__seed=0 (8 s)")  # plain text, not rich markup
        live.update()
    text = _ANSI.sub("", buf.getvalue())
    assert "\x1b[" in buf.getvalue()  # drawn for a terminal
    assert "[finished] algo=a__seed=0 (8 s)" in text
    assert "1/3 runs done, 44% of frames" in text
    last = text[text.rindex("1/3 runs done") :]
    for state, run_id in (("finished", "algo=a__seed=0"), ("running", "algo=a__seed=1"), ("pending", "algo=a__seed=2")):
        row = next(line for line in last.splitlines() if run_id in line)
        assert row.split()[:3] == [state, run_id, "100/600"] and "12.5" in row


def test_live_board_keeps_running_rows_when_the_terminal_is_short(tmp_path):
    from rich.console import Console

    board = _board(tmp_path, n=6)
    board.running = {"algo=a__seed=5"}
    console = Console(file=io.StringIO(), force_terminal=True, width=120, height=11)
    console.print(LiveBoard(board, console=console).renderable())
    text = _ANSI.sub("", console.file.getvalue())
    assert "algo=a__seed=5" in text and "3 more: 1 finished, 2 pending" in text


def test_live_only_on_a_terminal_outside_ci():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert use_live(Tty(), {}) and use_live(Tty(), {"TERM": "xterm"})
    assert not use_live(io.StringIO(), {})
    assert not use_live(Tty(), {"CI": "true"}) and not use_live(Tty(), {"TERM": "dumb"})


def test_launchers_that_cannot_use_the_url_say_so(tmp_path):
    from adarl.experiments.launchers import make_launcher
    from adarl.experiments.orchestrate import run_experiment

    with pytest.raises(AdaRLValueError, match="--submitit-folder"):
        make_launcher("submitit", output="s3://bucket/exp")
    assert make_launcher("submitit", output="s3://bucket/exp", submitit_folder=tmp_path).folder == tmp_path
    spec = tmp_path / "s.yaml"
    spec.write_text("kind: experiment\nname: s\nrecipe: quickstart\n")
    with pytest.raises(AdaRLValueError, match="memory:// lives in one process"):
        run_experiment(spec, output="memory://exp", launcher="ray", report=False, log=lambda *_: None)


def test_local_paths_keep_their_experiment_json(tmp_path):
    run = PlannedRun("seed=0", {}, 0, "quickstart", [], str(tmp_path / "seed=0"))
    assert "scratch" not in run.as_dict()
    run.scratch = "/fast"
    assert run.as_dict()["scratch"] == "/fast"
