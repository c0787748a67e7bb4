"""Faults a user or a cluster causes, through the `adarl` command: damaged and foreign checkpoints, evaluation
beside training records, two starts in one folder, a full disk and a read-only one.

Every row of docs/resuming.md's fault table names its test here (or in tests/test_reliability.py and
tests/test_run_dir.py); ``test_fault_table_rows_are_tests`` checks that. File-system faults run twice: on a real
tmpfs where this machine lets us mount one (small, or read-only), and under tests/faultfs.py's injected faults, which
need no privileges, so CI covers the same behaviour either way.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import re
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch
from _helpers import REPO, adarl, start_adarl, tiny, wait_for
from faultfs import FaultFS, adarl_under_faults, readonly_fs, remount, small_fs
from test_kill_resume import _results

from adarl.errors import AdaRLWarning, CheckpointError
from adarl.runtime.run_folder.run_dir import TRAINING_RECORDS, RunDir

# A few hundred frames: checkpoints at 100, 200 and the end, two rank events, best.pt before the second one.
FAST = tiny(
    "collector.total_frames=300",
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "rank.interval=100",
    "replay.size=1000",
    "replay.warm_start.frames=50",
    "eval.interval=150",
    "eval.max_steps=20",
    "checkpoint.interval=100",
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("faults") / "run"
    proc = adarl("run", "quickstart", *FAST, "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _one_error_line(proc: subprocess.CompletedProcess, *words: str) -> str:
    """The command failed with exactly one `adarl: error:` line holding ``words``, and no traceback."""
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("adarl: error:")]
    assert len(errors) == 1, proc.stderr[-3000:]
    for word in words:
        assert word in errors[0], (word, errors[0])
    return errors[0]


def _warnings(proc: subprocess.CompletedProcess) -> list[str]:
    return [line for line in proc.stderr.splitlines() if line.startswith("adarl: warning:")]


def _tree(path: Path) -> dict[str, str]:
    return {
        f.relative_to(path).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(path.rglob("*"))
        if f.is_file()
    }


def _is_training_record(rel: str) -> bool:
    return any(rel == r or (r.endswith("/") and rel.startswith(r)) for r in TRAINING_RECORDS)


# ------------------------------------------------------------------------------------------ damaged checkpoints


def test_resume_names_a_damaged_checkpoint_or_refuses_it(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    ckpts = RunDir(run).checkpoints()
    newest = ckpts[-1]
    newest.write_bytes(newest.read_bytes()[:1000])  # a write cut short
    proc = adarl("resume", str(run), "--checkpoint", "latest", "--quiet")
    _one_error_line(proc, newest.name, "truncated", "--checkpoint latest")
    assert newest.exists()  # insisting changes nothing
    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert f"skipped checkpoint {newest.name}" in line and "truncated" in line and ckpts[-2].name in line
    assert f"renamed {newest.name}.corrupt" in line
    assert newest.with_name(newest.name + ".corrupt").is_file()
    assert json.loads((run / "summary.json").read_text())["frames"] >= 300


class _Evil:
    def __reduce__(self):
        return (os.system, (f"touch {os.environ.get('ADARL_EVIL_MARKER', '/nonexistent/x')}",))


def test_eval_names_a_refused_checkpoint_and_renames_nothing(finished, tmp_path, monkeypatch):
    run = _copy(finished, tmp_path / "run")
    marker = tmp_path / "pwned"
    monkeypatch.setenv("ADARL_EVIL_MARKER", str(marker))
    evil = run / "checkpoints" / "ckpt-000000099999.pt"
    torch.save({"format": "adarl.checkpoint", "version": 1, "frames": 99999, "state": _Evil()}, evil)
    before = evil.read_bytes()
    proc = adarl("eval", str(run), "--episodes", "1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert evil.name in line and "Python object" in line and "weights_only" not in proc.stderr
    assert evil.read_bytes() == before  # evaluation renames nothing
    proc = adarl("eval", str(run), "--checkpoint", "latest", "--episodes", "1")
    _one_error_line(proc, evil.name, "Python object")
    assert "weights_only" not in proc.stderr
    assert not marker.exists()


@pytest.mark.parametrize("damage", ["missing", "emptied", "truncated", "python object", "fifo"])
def test_damaged_newest_replay_buffer_falls_back_like_a_missing_one(finished, tmp_path, damage):
    run = _copy(finished, tmp_path / "run")
    ckpts = RunDir(run).checkpoints()
    newest = ckpts[-1]
    rb = RunDir._replay_buffer_dir(newest)
    buffer = rb / "buffer.pt"
    if damage == "missing":
        shutil.rmtree(rb)
    elif damage == "emptied":  # killed while the buffer was written again at the same frames (found under submitit)
        buffer.unlink()
    elif damage == "truncated":
        buffer.write_bytes(buffer.read_bytes()[: buffer.stat().st_size // 2])  # a copy or a disk cut it short
    elif damage == "python object":
        torch.save({"_storage": _Evil()}, buffer)
    else:
        buffer.unlink()
        os.mkfifo(buffer)  # reading it would wait forever for a writer
    proc = adarl("resume", str(run), "--checkpoint", "latest", "--quiet", timeout=300)
    _one_error_line(proc, newest.name, "has lost its replay buffer", "--checkpoint latest")
    proc = adarl("resume", str(run), "--quiet", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert line.startswith(
        f"adarl: warning: skipped checkpoint {newest.name} (renamed {newest.name}.corrupt): has lost"
    )
    assert f"using {ckpts[-2].name} instead" in line
    assert {"truncated": "truncated", "python object": "Python object", "fifo": "a FIFO"}.get(damage, "") in line
    assert newest.with_name(newest.name + ".corrupt").exists()  # set aside (the resumed run writes its own again)
    assert json.loads((run / "summary.json").read_text())["frames"] >= 300


def test_fifo_in_place_of_the_newest_checkpoint_is_refused_unread(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    ckpts = RunDir(run).checkpoints()
    newest = ckpts[-1]
    newest.unlink()
    os.mkfifo(newest)  # torch.load of it waited forever for a writer: `adarl eval` hung
    proc = adarl("eval", str(run), "--episodes", "1", timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert newest.name in line and "not a regular file (a FIFO)" in line and f"using {ckpts[-2].name}" in line
    assert stat.S_ISFIFO(newest.stat().st_mode)  # evaluation renames nothing
    proc = adarl("eval", str(run), "--checkpoint", "latest", "--episodes", "1", timeout=300)
    _one_error_line(proc, newest.name, "not a regular file (a FIFO)")


# ------------------------------------------------------------------------------------------ foreign checkpoints


def _foreign_checkpoint(tmp_path: Path, *, fingerprint: bool = True) -> Path:
    """A checkpoint of the same recipe with other widths (32 instead of 64): what a copy from another run is."""
    from adarl.runtime.config import load_recipe, save_resolved
    from adarl.runtime.trainers import OffPolicyTrainer

    recipe = load_recipe("quickstart", [*FAST, "network.actor.num_cells=[32,32]", "network.critic.num_cells=[32,32]"])
    other = RunDir.create(tmp_path / "other")
    save_resolved(recipe, other.recipe_path)
    trainer = OffPolicyTrainer(recipe, other, quiet=True)
    path = trainer.save_checkpoint()
    trainer.close()
    if not fingerprint:  # as written before checkpoints named their recipe
        payload = torch.load(path, weights_only=True)
        del payload["recipe_fingerprint"]
        torch.save(payload, path)
    return path


def test_foreign_checkpoint_is_refused_by_name_before_loading(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    foreign = _foreign_checkpoint(tmp_path)
    copied = run / "checkpoints" / "ckpt-000000099999.pt"
    shutil.copy(foreign, copied)
    proc = adarl("eval", str(run), "--checkpoint", str(foreign), "--episodes", "1")
    _one_error_line(proc, foreign.name, "another recipe", "network.actor.num_cells: [32, 32] in it, [64, 64]")
    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert copied.name in line and "another recipe" in line
    assert copied.with_name(copied.name + ".corrupt").is_file()


def test_foreign_checkpoint_without_fingerprint_is_one_line(finished, tmp_path):
    foreign = _foreign_checkpoint(tmp_path, fingerprint=False)
    proc = adarl("eval", str(finished), "--checkpoint", str(foreign), "--episodes", "1")
    _one_error_line(proc, foreign.name, "does not fit this run's recipe")


# ------------------------------------------------------------------------------------------ evaluation and reports


@pytest.mark.parametrize(
    "command, allowed",
    [
        (["eval", "--checkpoint", "best", "--episodes", "1"], {"eval_nominal.json"}),
        (["eval", "--episodes", "1"], {"eval_nominal.json"}),
        (["eval", "--sweep", "torso_length=0.3:0.5:2", "--episodes", "1"], {"sweeps/"}),
        (
            ["report"],
            {"report.md", *(f"plots/{f}.{x}" for f in ("return", "ranks", "speed") for x in ("png", "pdf", "svg"))},
        ),
    ],
)
def test_eval_and_report_leave_training_records_unchanged(finished, tmp_path, command, allowed):
    run = _copy(finished, tmp_path / "run")
    before = _tree(run)
    assert "ranks.csv" in before and len(json.loads((run / "ranks.json").read_text())) == 2
    proc = adarl(command[0], str(run), *command[1:])
    assert proc.returncode == 0, proc.stderr[-3000:]
    after = _tree(run)
    changed = {k for k in before.keys() | after.keys() if before.get(k) != after.get(k)}
    assert all(any(k == a or k.startswith(a) for k in after) for a in allowed), "its output is missing"
    unexpected = {
        k for k in changed if k not in allowed and not any(a.endswith("/") and k.startswith(a) for a in allowed)
    }
    assert not unexpected, unexpected
    assert not any(_is_training_record(k) for k in changed)
    assert {k for k in after if _is_training_record(k)} == {k for k in before if _is_training_record(k)}


# ------------------------------------------------------------------------------------------ concurrent starts


def test_two_runs_started_at_once_cannot_share_a_folder(tmp_path):
    out = tmp_path / "same"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "adarl.cli", "run", "quickstart", *FAST, f"seed={seed}", "-o", str(out), "--quiet"],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for seed in (0, 7)
    ]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(rc for rc, _ in results)
    assert codes == [0, 1], results
    winner = [seed for (rc, _), seed in zip(results, (0, 7)) if rc == 0][0]
    loser_err = [err for rc, err in results if rc != 0][0]
    assert "Traceback" not in loser_err and re.search(r"already exists|claimed by another process", loser_err)
    assert f"seed: {winner}\n" in (out / "recipe.yaml").read_text()
    steps = [line.split(",")[0] for line in (out / "metrics/scalars/time/episodes.csv").read_text().split()[1:]]
    assert len(steps) == len(set(steps)), "metric rows written twice"


def test_resume_refuses_a_folder_another_process_trains_in(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from adarl.runtime.run_folder.run_dir import RunDir; "
            "RunDir(sys.argv[1]).lock(); print('locked', flush=True); time.sleep(120)",
            str(run),
        ],
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = adarl("resume", str(run), "--quiet")
        _one_error_line(proc, "in use by another process", f"pid {holder.pid}")
        proc = adarl("run", "quickstart", *FAST, "-o", str(run), "--overwrite", "--quiet")
        _one_error_line(proc, "in use by another process")
        assert (run / "summary.json").is_file()  # --overwrite removed nothing
    finally:
        holder.kill()
        holder.wait()


# ------------------------------------------------------------------------------------------ killed, deleted, signalled


def test_kill_9_before_the_first_checkpoint_resumes_from_frame_0(finished, tmp_path):
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    try:
        assert wait_for(lambda: (run / "recipe.yaml").is_file(), proc, poll=0.002), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGSTOP)  # its first moments: the recipe written, the networks being built
        assert not list(run.glob("checkpoints/ckpt-*")), "the frame-0 checkpoint came first: nothing to test"
    finally:
        proc.kill()
        proc.wait()
    proc = adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    _one_error_line(proc, "already exists", f"adarl resume {run}")  # points at resume, and resume goes on:
    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    [line] = _warnings(proc)
    assert "has no checkpoint" in line and "starting it from frame 0" in line
    assert _results(run) == _results(finished)  # the same run, bit for bit, as one never stopped


def test_kill_9_before_the_recipe_is_written_leaves_a_folder_adarl_run_takes(tmp_path):
    run = tmp_path / "run"
    claim_and_die = (
        "import os, sys; from adarl.runtime.run_folder.run_dir import RunDir; RunDir.create(sys.argv[1]); "
        "os.kill(os.getpid(), 9)"  # killed between claiming the folder and writing recipe.yaml
    )
    proc = subprocess.run([sys.executable, "-c", claim_and_die, str(run)], env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == -signal.SIGKILL and [p.name for p in run.iterdir()] == [".adarl.lock"]
    proc = adarl("resume", str(run), "--quiet")
    _one_error_line(proc, "holds no recipe.yaml", f"adarl run RECIPE -o {run}")  # points at run, and run goes on:
    proc = adarl("run", "quickstart", *FAST, "collector.total_frames=100", "-o", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((run / "summary.json").read_text())["frames"] >= 100


def test_run_folder_deleted_mid_run_stops_and_recreates_nothing(tmp_path):
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    try:
        assert wait_for(lambda: bool(RunDir(run).checkpoints()), proc, poll=0.002), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGSTOP)  # training: the frame-0 checkpoint is written
        shutil.rmtree(run)  # `rm -rf RUN_DIR` in another terminal
        proc.send_signal(signal.SIGCONT)
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    done = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    _one_error_line(done, "was deleted or moved while this process trained in it", "recreated nothing")
    assert "run finished" not in out
    assert not run.exists(), sorted(p.relative_to(run).as_posix() for p in run.rglob("*"))


def test_sigterm_while_the_report_is_written_finishes_it_and_stops_cleanly(tmp_path):
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    try:
        assert wait_for(lambda: (run / "summary.json").is_file(), proc, poll=0.002), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGSTOP)  # summary.json is written first, then the plots and report.md
        assert not (run / "report.md").exists(), "the report was already written: nothing to test"
        proc.send_signal(signal.SIGTERM)  # delivered as it goes on writing the report
        proc.send_signal(signal.SIGCONT)
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert "Traceback" not in err and "leaked semaphore" not in err, err[-3000:]
    [line] = [line for line in err.splitlines() if line.startswith("adarl: error:")]
    assert "stopped on SIGTERM at the end of the run" in line and "report.md" in line
    assert (run / "report.md").is_file() and (run / "plots" / "return.png").is_file()
    assert json.loads((run / "summary.json").read_text())["frames"] >= 300


def test_resumed_run_times_every_process(tmp_path):
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    first = run / "checkpoints" / "ckpt-000000000100.pt"
    assert wait_for(first.is_file, proc, poll=0.002), proc.communicate()[1][-3000:]
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.kill()
    proc.wait()
    before = RunDir(run).load_checkpoint(RunDir(run).checkpoints()[-1], replay_buffer=False)["counters"]
    assert before["wall_time_s"] > 0  # the checkpoint carries the wall time so far
    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["wall_time_s"] > before["wall_time_s"]  # both processes, not the last one alone
    assert summary["updates_per_s"] == pytest.approx(summary["updates"] / summary["wall_time_s"])
    report = (run / "report.md").read_text()
    assert f"wall time: {summary['wall_time_s']:.0f} s ({summary['updates_per_s']:.1f} updates/s)" in report


class _Stderr:
    """A background process's stderr, read as it comes (the progress bar, adarl's notices): what a test waits on."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.chunks: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        while chunk := proc.stderr.read(1):  # returns as soon as something is there
            self.chunks.append(chunk)

    @property
    def text(self) -> str:
        return "".join(self.chunks)

    def done(self) -> str:
        self._thread.join(timeout=60)
        return self.text


def _error_lines(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if line.strip().startswith("adarl: error:")]


@pytest.mark.parametrize("when", ["while its batch runs", "once the stop has begun"])
def test_a_second_sigint_never_gives_a_traceback_and_the_run_resumes_exactly(finished, tmp_path, when):
    """Issue 46.8: SIGINT twice 0.5 s apart ended about one try in four with a traceback (a tensordict RuntimeError,
    a KeyboardInterrupt in an exit handler) or killed by the signal (exit -2). A second signal while the batch runs
    stops at once (its previous checkpoint kept); once the stop has begun (its checkpoint being written) it is
    ignored. Either way: exit 130, one line, and the run resumes to the very run never stopped."""
    run = tmp_path / "run"
    proc = start_adarl("run", "quickstart", *FAST, "-o", str(run))  # not --quiet: its notices are the events waited on
    err = _Stderr(proc)
    try:
        first = run / "checkpoints" / "ckpt-000000000100.pt"
        assert wait_for(first.is_file, proc, poll=0.002), err.text[-3000:]
        proc.send_signal(signal.SIGSTOP)  # the first signal lands in training, 100 frames in (the run has 300)
        proc.send_signal(signal.SIGINT)
        proc.send_signal(signal.SIGCONT)
        event = "SIGINT received" if when == "while its batch runs" else "adarl: stopping:"
        assert wait_for(lambda: event in err.text, proc, poll=0.002), err.text[-3000:]
        proc.send_signal(signal.SIGINT)  # at once: in the batch, or as the checkpoint is written and the run closes
        proc.wait(timeout=300)
    finally:
        proc.kill()
    text = err.done()
    assert proc.returncode == 130, (proc.returncode, text[-3000:])
    assert "Traceback" not in text and "Exception ignored" not in text, text[-3000:]
    [line] = _error_lines(text)
    if when == "once the stop has begun":
        assert re.search(r"stopped on SIGINT at \d+ frames; checkpoint ckpt-\d+\.pt saved", line), line
    else:
        assert "stopped on SIGINT at" in line or "interrupted (stopped at once" in line, line
    done = adarl("resume", str(run), "--quiet")
    assert done.returncode == 0, done.stderr[-3000:]
    assert _results(run) == _results(finished)  # the same run, bit for bit, as one never stopped


def test_sighup_checkpoints_and_stops_as_sigterm_does(finished, tmp_path):
    """Issue 46.8: SIGHUP (the terminal or SSH session closed) killed the run like kill -9, without a checkpoint; it
    checkpoints after its batch and exits 129 (128 + SIGHUP), and the run resumes exactly."""
    run = tmp_path / "run"
    previous = signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a suite under `nohup` would start it with SIGHUP ignored
    try:
        proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
    finally:
        signal.signal(signal.SIGHUP, previous)
    try:
        first = run / "checkpoints" / "ckpt-000000000100.pt"
        assert wait_for(first.is_file, proc, poll=0.002), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGSTOP)  # delivered in training, 100 frames in (the run has 300)
        proc.send_signal(signal.SIGHUP)
        proc.send_signal(signal.SIGCONT)
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGHUP, (proc.returncode, err[-3000:])
    assert "Traceback" not in err, err[-3000:]
    [line] = _error_lines(err)
    stopped = re.search(r"stopped on SIGHUP at (\d+) frames; checkpoint (ckpt-\d+\.pt) saved", line)
    assert stopped and int(stopped.group(1)) >= 100, line  # after its batch (the one at 100 had just checkpointed)
    assert (run / "checkpoints" / stopped.group(2)).is_file()
    done = adarl("resume", str(run), "--quiet")
    assert done.returncode == 0, done.stderr[-3000:]
    assert _results(run) == _results(finished)


# ------------------------------------------------------------------------------------------ someone else's folder


def test_overwrite_refuses_a_folder_adarl_did_not_write(finished, tmp_path):
    thesis = tmp_path / "thesis"
    (thesis / "figures").mkdir(parents=True)
    (thesis / "thesis.tex").write_text("\\documentclass{book}\n")
    (thesis / "figures" / "plot.pdf").write_bytes(b"%PDF-1.5\n")
    before = _tree(thesis)
    proc = adarl("run", "quickstart", *FAST, "-o", str(thesis), "--overwrite", "--quiet")
    _one_error_line(proc, "--overwrite refused", "figures/, thesis.tex", "nothing was deleted")
    proc = adarl("run", "quickstart", *FAST, "-o", str(thesis), "--quiet")
    line = _one_error_line(proc, "already exists", "figures/, thesis.tex")
    assert "adarl resume" not in line  # not a run: nothing to resume
    assert _tree(thesis) == before
    run = _copy(finished, tmp_path / "run")  # a run folder with someone's notes in it: the notes are not adarl's
    (run / "notes.md").write_text("seed 0 looked odd\n")
    before = _tree(run)
    proc = adarl("run", "quickstart", *FAST, "-o", str(run), "--overwrite", "--quiet")
    _one_error_line(proc, "--overwrite refused", "notes.md")
    assert _tree(run) == before


# ------------------------------------------------------------------------------------------ disk full


def _check_stopped_cleanly(run: Path, proc: subprocess.CompletedProcess) -> None:
    line = _one_error_line(proc, "adarl resume")
    assert "disk full" in line or "No space left" in line
    assert not [p for p in run.rglob("*") if p.name.endswith(".tmp")], "partial files left"
    rd = RunDir(run)
    last = rd.checkpoints()[-1]
    state = rd.load_checkpoint(last)  # the previous checkpoint is complete, with its buffer when it has one
    assert int(state["counters"]["frames"]) in (0, 100)


def test_disk_full_tmpfs_stops_with_one_line_and_resumes(tmp_path):
    with small_fs("3m", tmp=tmp_path) as fs:
        run = fs / "run"  # a 1 MB replay buffer: the checkpoint at 200 frames no longer fits
        proc = adarl("run", "quickstart", *FAST, "replay.size=6000", "-o", str(run), "--quiet")
        assert proc.returncode != 135, "SIGBUS: the replay buffer was memory-mapped onto the full disk"
        _check_stopped_cleanly(run, proc)
        remount(fs, "size=32m")  # space freed: the run goes on from its last checkpoint
        proc = adarl("resume", str(run), "--quiet")
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert json.loads((run / "summary.json").read_text())["frames"] >= 300


def test_disk_full_names_the_file_it_could_not_write(tmp_path):
    with small_fs("8m", tmp=tmp_path) as fs:
        run = fs / "run"
        proc = start_adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet")
        try:
            assert wait_for(lambda: bool(RunDir(run).checkpoints()), proc, poll=0.002), proc.communicate()[1][-3000:]
            proc.send_signal(signal.SIGSTOP)
            with (fs / "filler").open("wb") as fh, pytest.raises(OSError):  # the disk fills up while it trains
                while True:
                    fh.write(b"\0" * (64 << 10))
                    fh.flush()
            proc.send_signal(signal.SIGCONT)
            out, err = proc.communicate(timeout=300)
        finally:
            proc.kill()
        line = _one_error_line(subprocess.CompletedProcess(proc.args, proc.returncode, out, err), "adarl resume")
        assert re.search(rf"'{re.escape(str(run))}/[^']+': No space left on device", line), line


def test_disk_full_injected_stops_with_one_line(tmp_path):
    run = tmp_path / "run"  # 1.2 MB of writes: the run folder, the frame-0 checkpoint, then the buffer at 100 frames
    proc = adarl_under_faults(
        tmp_path,
        "full",
        1_200_000,
        ["run", "quickstart", *FAST, "replay.size=6000", "-o", str(run), "--quiet"],
        timeout=300,
    )
    _check_stopped_cleanly(run, proc)


def test_disk_full_while_logging_metrics_is_one_line(tmp_path):
    run = tmp_path / "run"  # the metric files' disk is full from the start: the first row fails
    proc = adarl_under_faults(
        run / "metrics", "full", 0, ["run", "quickstart", *FAST, "-o", str(run), "--quiet"], timeout=300
    )
    line = _one_error_line(proc, "metrics/scalars/", "disk full", "its last checkpoint is intact", "adarl resume")
    assert "No space left on device" in line
    assert [p.name for p in RunDir(run).checkpoints()] == ["ckpt-000000000000.pt"]
    RunDir(run).load_checkpoint(RunDir(run).checkpoints()[-1])


_DUMP = """
import sys, torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
import adarl.runtime.run_folder.run_dir as rd
from adarl.errors import CheckpointError
root, check = sys.argv[1], sys.argv[2] == "check"
if not check:
    rd.check_free_space = lambda *a: None  # let the write itself meet the full disk
rb = TensorDictReplayBuffer(storage=LazyTensorStorage(20000), batch_size=4)
rb.extend(TensorDict({"obs": torch.randn(20000, 40)}, [20000]))  # 3.2 MB on a 3 MB disk
run = rd.RunDir.create(root + "/run")
run.save_checkpoint({"counters": {"frames": 1}}, frames=1)
try:
    run.save_checkpoint({"counters": {"frames": 2}}, frames=2, replay_buffer=rb)
except CheckpointError as err:
    print("REFUSED", err)
"""


@pytest.mark.parametrize("check", ["check", "write"])
def test_replay_buffer_dump_on_a_full_tmpfs_is_an_error_not_sigbus(tmp_path, check):
    with small_fs("3m", tmp=tmp_path) as fs:
        proc = subprocess.run(
            [sys.executable, "-c", _DUMP, str(fs), check],
            capture_output=True,
            text=True,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            timeout=120,
        )
        assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])  # 135 = SIGBUS
        assert "REFUSED" in proc.stdout and "disk full" in proc.stdout
        assert sorted(p.name for p in (fs / "run" / "checkpoints").iterdir()) == ["ckpt-000000000001.pt"]


def test_replay_buffer_dump_injected_full_disk(tmp_path):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(5000), batch_size=4)
    rb.extend(TensorDict({"obs": torch.randn(5000, 40)}, [5000]))  # 0.8 MB
    run = RunDir.create(tmp_path / "run")
    run.save_checkpoint({"counters": {"frames": 1}}, frames=1, replay_buffer=rb)
    with FaultFS(tmp_path, "full", budget=300_000), pytest.raises(CheckpointError, match="disk full") as info:
        run.save_checkpoint({"counters": {"frames": 2}}, frames=2, replay_buffer=rb)
    assert "ckpt-000000000001.pt is intact" in str(info.value)
    names = sorted(p.name for p in run.checkpoint_dir.iterdir())
    assert names == ["ckpt-000000000001.pt", "rb-000000000001"]
    fresh = TensorDictReplayBuffer(storage=LazyTensorStorage(5000), batch_size=4)
    assert run.load_replay_buffer(fresh, frames=1) and len(fresh) == 5000


# ------------------------------------------------------------------------------------------ read-only


def _readonly_cases(ro: Path) -> dict[str, subprocess.CompletedProcess]:
    return {
        "run": adarl("run", "quickstart", *FAST, "-o", str(ro / "new"), "--quiet"),
        "resume": adarl("resume", str(ro / "run"), "--quiet"),
        "eval": adarl("eval", str(ro / "run"), "--episodes", "1"),
    }


def _check_readonly(ro: Path, procs: dict[str, subprocess.CompletedProcess]) -> None:
    _one_error_line(procs["run"], "cannot create run folder", "Read-only file system")
    _one_error_line(procs["resume"], "cannot lock run folder", "Read-only file system")
    _one_error_line(procs["eval"], "eval_nominal.json", "Read-only file system")
    assert not (ro / "new").exists()


def test_read_only_tmpfs_is_one_line(finished, tmp_path):
    with readonly_fs(tmp=tmp_path, populate=lambda fs: shutil.copytree(finished, fs / "run")) as ro:
        _check_readonly(ro, _readonly_cases(ro))


def test_read_only_injected_is_one_line(finished, tmp_path):
    ro = tmp_path / "ro"
    _copy(finished, ro / "run")
    procs = {
        "run": adarl_under_faults(ro, "readonly", 0, ["run", "quickstart", *FAST, "-o", str(ro / "new"), "-q"]),
        "resume": adarl_under_faults(ro, "readonly", 0, ["resume", str(ro / "run"), "--quiet"]),
        "eval": adarl_under_faults(ro, "readonly", 0, ["eval", str(ro / "run"), "--episodes", "1"]),
    }
    _check_readonly(ro, procs)


# ------------------------------------------------------------------------------------------ experiments


def test_experiment_axis_that_changes_nothing_is_warned_about(tmp_path):
    from adarl.experiments.spec import load_experiment, plan_runs

    spec = tmp_path / "exp.yaml"
    spec.write_text(
        "kind: experiment\nname: x\nrecipe: quickstart\nseeds: [0]\n"
        "axes:\n  rank: [4, 8]\n  replicate: [a, b]\noverrides: ['network.actor.rank={rank}']\n"
    )
    with pytest.warns(AdaRLWarning, match="axis 'replicate' changes nothing") as caught:
        runs = plan_runs(load_experiment(spec), tmp_path / "out")
    assert len(runs) == 4 and not any("'rank'" in str(w.message) for w in caught)
    proc = adarl("experiment", str(spec), "--dry-run", "-o", str(tmp_path / "out"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert [line for line in _warnings(proc) if "'replicate' changes nothing" in line]


@pytest.mark.parametrize(
    "values, name, value, allowed",
    [
        ("{torso_length: 1e308}", "torso_length", "1e+308", ">= 0.02 and <= 2"),
        ("{mass_scale: 1e-300}", "mass_scale", "1e-300", ">= 0.01 and <= 100"),
    ],
)
def test_physically_impossible_value_is_refused_before_a_run_folder(tmp_path, values, name, value, allowed):
    """Issue 30.7: refused by `adarl show` and `adarl run` naming the parameter, the value and the allowed range; no
    MuJoCo traceback, no run folder."""
    override = f"env.perturbation.schedule={{kind: fixed, values: {values}}}"
    for proc in (
        adarl("show", "quickstart", override),
        adarl("run", "quickstart", override, "-o", str(tmp_path / "r")),
    ):
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-3000:]  # 2: an invalid recipe
        (line,) = [line for line in proc.stderr.splitlines() if line.startswith("adarl: error:")]
        assert all(word in line for word in (name, value, allowed, "env.perturbation.schedule")), line
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------------------------------ names, commands, budget


def test_an_output_folder_name_over_255_bytes_is_one_line_naming_the_limit(tmp_path):
    """Issue 46.9: an output folder named with 300 characters gave an OSError traceback (errno 36, ENAMETOOLONG, is
    a name the file system cannot hold, not a failing disk): one line naming the limit, exit 2, nothing written."""
    spec = tmp_path / "exp.yaml"
    spec.write_text("kind: experiment\nname: x\nrecipe: quickstart\nseeds: [0]\n")
    long = tmp_path / ("a" * 300)
    for args in (
        ["run", "quickstart", *FAST, "-o", str(long), "--quiet"],
        ["resume", str(long), "--quiet"],
        ["eval", str(long)],
        ["experiment", str(spec), "-o", str(long), "--no-live"],
    ):
        proc = adarl(*args)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, (args, proc.stderr[-3000:])
        [line] = _error_lines(proc.stderr)
        assert "too long" in line and "300 bytes" in line and "at most 255 bytes" in line, line
    assert [p.name for p in tmp_path.iterdir()] == ["exp.yaml"]


def _commands(text: str) -> list[list[str]]:
    """Every command a message suggests (between backticks), as the shell would split it."""
    return [shlex.split(c) for c in re.findall(r"`(adarl [^`]*)`", text)]


def test_suggested_commands_are_quoted_for_the_shell(finished, tmp_path):
    """Issue 46.9: a folder named `a b;rm -rf x` gave `adarl resume .../a b;rm -rf x`, which a shell runs as
    `adarl resume .../a b` then `rm -rf x`. Every command adarl suggests is quoted (shlex): pasted, it runs what it
    says, with the folder as one argument."""
    run = _copy(finished, tmp_path / "a b;rm -rf x")
    exists = _one_error_line(adarl("run", "quickstart", *FAST, "-o", str(run), "--quiet"), "already exists")
    assert _commands(exists) == [["adarl", "resume", str(run)]]
    changed = adarl("resume", str(run), "rank.beta=0.5", "--quiet")
    assert changed.returncode == 2, changed.stderr[-3000:]
    assert _commands(changed.stderr) == [["adarl", "run", str(run / "recipe.yaml"), "rank.beta=0.5", "-o", "NEW_DIR"]]
    complete = adarl("resume", str(run), "--quiet")
    assert complete.returncode == 0 and "already complete" in complete.stdout, complete.stderr[-3000:]
    assert _commands(complete.stdout) == [["adarl", "resume", str(run), "collector.total_frames=N"]]


# The only rank event at update 500, in the last batch (updates start at 200 frames, 100 per 100-frame batch).
LAST_BATCH_EVENT = tiny(
    "rank.interval=500", "eval.interval=600", "eval.episodes=1", "eval.max_steps=20", "checkpoint.interval=600"
)


@pytest.mark.parametrize("counted", ["true", "false"])
def test_a_warm_start_never_runs_past_the_frame_budget(tmp_path, counted):
    """Issue 46.9: a rank event in the last batch warm-started after it, past the budget: total_frames=600 ended at
    700 frames, and resume then reported 700. Counted warm-start frames stop at the budget; uncounted ones
    (``count_frames=false``, every committed experiment's setting) run exactly as before: the numbers below are the
    code's before the fix."""
    run = tmp_path / "run"
    proc = adarl(
        "run", "quickstart", *LAST_BATCH_EVENT, f"replay.warm_start.count_frames={counted}", "-o", str(run), "--quiet"
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    got = {k: summary[k] for k in ("frames", "env_frames", "warm_start_frames", "updates", "rank_events")}
    if counted == "true":  # the event's warm start has no budget left: it collects nothing
        assert got == {"frames": 600, "env_frames": 600, "warm_start_frames": 0, "updates": 500, "rank_events": 1}
    else:  # as before the fix: 100 warm-start frames beside the 600 the budget counts
        assert got == {"frames": 600, "env_frames": 700, "warm_start_frames": 100, "updates": 500, "rank_events": 1}
    proc = adarl("resume", str(run), "--quiet")
    assert proc.returncode == 0 and "already complete: 600 frames of collector.total_frames=600" in proc.stdout


# ------------------------------------------------------------------------------------------ the documented table


def _defined_tests() -> set[str]:
    found = set()
    for f in (REPO / "tests").glob("test_*.py"):
        for node in ast.parse(f.read_text()).body:
            if isinstance(node, ast.FunctionDef) and node.name.startswith("test_"):
                found.add(f"{f.name}::{node.name}")
    return found


def test_fault_table_rows_are_tests():
    text = (REPO / "docs" / "resuming.md").read_text()
    table = text.split("## Faults and what you see", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("|") and not set(line) <= set("|-: ")][1:]
    assert len(rows) >= 15
    defined = _defined_tests()
    for row in rows:
        # a test, or one case of a parametrised test: `test_x.py::test_y[case]`
        names = re.findall(r"`(test_\w+\.py::test_\w+)(?:\[([^\]`]+)\])?`", row)
        assert names, f"fault table row without a test: {row}"
        for name, case in names:
            assert name in defined, f"{name} (docs/resuming.md) is not a test"
            source = (REPO / "tests" / name.split("::")[0]).read_text()
            assert not case or f'"{case}"' in source, f"{name}[{case}] (docs/resuming.md): no such case"
