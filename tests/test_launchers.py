"""Launchers: a tiny 2-algorithm x 2-seed experiment through Ray (one worker killed mid-run) and through submitit's
local executor gives every run finished exactly once and the same report as the local launcher; so does the local
launcher writing to an fsspec URL, with one run killed mid-run and resumed on a fresh scratch folder."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from _helpers import tiny, wait_for

from adarl.errors import AdaRLError, AdaRLValueError
from adarl.experiments.execute import read_attempts
from adarl.experiments.launchers import make_launcher
from adarl.experiments.orchestrate import run_experiment
from adarl.experiments.progress import ProgressBoard
from adarl.experiments.spec import load_experiment, plan_runs

REPO = Path(__file__).resolve().parents[1]
# ~8 s per run on one core; a checkpoint every 50 frames so a killed run resumes from mid-run.
TINY = tiny(
    "collector.lean=false",
    "collector.init_random_frames=100",
    "collector.frames_per_batch=50",
    "replay.warm_start.frames=50",
    "eval.interval=200",
    "eval.episodes=1",
    "eval.max_steps=30",
    "checkpoint.interval=50",
    "checkpoint.keep_last=2",
)


def _spec(tmp_path: Path) -> Path:
    spec = {
        "kind": "experiment",
        "name": "tiny",
        "recipe": "quickstart",
        "overrides": TINY,
        "axes": {
            "algorithm": [
                {"name": "adarl"},
                {
                    "name": "fixed4",
                    "overrides": ["rank.enabled=false", "network.actor.rank=4", "network.critic.rank=4"],
                },
            ]
        },
        "seeds": [0, 1],
        "workers": 2,
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


@pytest.fixture(autouse=True)
def _one_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("PYTHONPATH", str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def _report_content(out: Path) -> dict[str, str]:
    """The aggregate report's results (table, and every run's evaluations), without timings."""
    with (out / "report" / "table.csv").open() as fh:
        table = sorted(tuple(r.items()) for r in csv.DictReader(fh))
    evals = {p.parent.name: p.read_text() for p in sorted(out.glob("*/eval.csv"))}
    return {"table": repr(table), **evals}


def _assert_each_finished_once(out: Path, runs) -> None:
    for r in runs:
        ends = [e for e in read_attempts(out, r.run_id) if e["event"] == "end" and e["status"] == "finished"]
        assert len(ends) == 1, (r.run_id, read_attempts(out, r.run_id))


@pytest.fixture(scope="module")
def local_reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("local")
    out = tmp / "exp"
    runs = run_experiment(_spec(tmp), output=out, log=lambda *_: None)
    assert sorted(r.status for r in runs) == ["finished"] * 4
    return out, _report_content(out)


def test_make_launcher_rejects_unknown_names_and_bad_sizes():
    with pytest.raises(AdaRLValueError, match="unknown launcher 'slurmx'; choose one of local, ray, submitit"):
        make_launcher("slurmx")
    with pytest.raises(AdaRLValueError, match="workers must be >= 1"):
        make_launcher("local", workers=0)


def test_cli_rejects_an_unknown_launcher(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "adarl.cli",
            "experiment",
            str(_spec(tmp_path)),
            "--launcher",
            "k8s",
            "-o",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode != 0 and "invalid choice: 'k8s'" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_progress_board_lines_and_bar(tmp_path, local_reference):
    out, _ = local_reference
    runs = plan_runs(load_experiment(_spec(tmp_path)), out)
    runs[0].status = "finished"
    lines = ProgressBoard(runs).render()
    assert len(lines) == 5
    # 600/600: a warm start in the last batch no longer runs past the budget (it ended at 650, issue 46.9)
    assert lines[0].split()[0] == "finished" and "frames 600/600" in lines[0] and "return" in lines[0]
    assert lines[-1].startswith("[") and "1/4 runs done" in lines[-1]


def _experiment_cli(spec: Path, out: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "adarl.cli", "experiment", str(spec), "-o", str(out), "--no-live", *args]


def _wait_for(condition, what: str, proc: subprocess.Popen, limit_s: float = 600) -> None:
    """Poll ``condition`` until it holds (a generous limit: a loaded machine starts Ray slowly); fail at once if
    ``proc`` ends first."""
    if not wait_for(condition, proc, limit_s):
        assert proc.poll() is None, f"the experiment ended before its {what}: {proc.communicate()[1][-2000:]}"
        raise AssertionError(f"no {what} in {limit_s} s")


def _events(out: Path, run_id: str) -> list[dict]:
    try:
        return read_attempts(out, run_id)
    except ValueError:  # a line being written
        return []


def _checkpointed_mid_run(out: Path) -> bool:
    """Some run of the experiment in ``out`` has a checkpoint past frame 0."""
    return any(int(c.stem.split("-")[1]) > 0 for c in out.glob("*/checkpoints/ckpt-*.pt"))


def _stopped_on_sigint(proc: subprocess.Popen, out: Path, *waits) -> dict[str, str]:
    """Wait for each ``(condition, what)`` of ``waits``, send the experiment SIGINT, and return its runs' statuses
    after it: it exited 130 saying how to resume; each run that had started stopped after a checkpoint
    (``interrupted``, never "at once") or had finished, the others never started (``pending``); no training process
    and no stop request is left."""
    try:
        for condition, what in waits:
            _wait_for(condition, what, proc)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGINT, err[-3000:]
    assert "experiment stopped on SIGINT" in err and "run the same `adarl experiment` command" in err, err[-2000:]
    assert _training_pids(str(out)) == []
    assert not list(out.glob(".*.stop")) and not list(out.parent.glob(".*.stop"))
    runs = {r["run_id"]: r for r in json.loads((out / "experiment.json").read_text())["runs"]}
    state = {r: runs[r]["status"] for r in runs}
    assert "interrupted" in state.values(), state
    for r, status in state.items():
        assert status in ("interrupted", "pending", "finished"), state
        log = out / f"{r}.log"
        if status == "interrupted" and log.is_file():  # (none: stopped before its training process started)
            assert "stopped at once" not in log.read_text(), r
    return state


@pytest.mark.slow
def test_ray_launcher_survives_a_killed_worker_stops_on_sigint_and_resumes_to_local_results(tmp_path, local_reference):
    """``adarl experiment --launcher ray``: a Ray worker killed mid-run is retried from the run's checkpoint; a
    SIGINT then stops the experiment (the running runs checkpoint through their stop files, no other starts); the same
    command resumes every run to the local launcher's results, each finished once."""
    pytest.importorskip("ray")
    _, ref_report = local_reference
    out, spec = tmp_path / "exp", _spec(tmp_path)
    proc = subprocess.Popen(
        _experiment_cli(spec, out, "--launcher", "ray"),
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    killed: list[str] = []

    def a_worker_killed_mid_run() -> bool:
        for f in sorted((out / "attempts").glob("*.jsonl")) if (out / "attempts").is_dir() else []:
            events, run = _events(out, f.stem), out / f.stem
            ckpts = list((run / "checkpoints").glob("ckpt-*.pt")) if (run / "checkpoints").is_dir() else []
            if len(events) == 1 and any(int(c.stem.split("-")[1]) > 0 for c in ckpts):
                os.kill(events[0]["pid"], signal.SIGKILL)  # the Ray worker process running this run
                killed.append(f.stem)
                return True
        return False

    def retried() -> bool:
        return [e["event"] for e in _events(out, killed[0])][-1:] == ["start"] and len(_events(out, killed[0])) > 1

    state = _stopped_on_sigint(
        proc, out, (a_worker_killed_mid_run, "run with a checkpoint to kill"), (retried, "retry of the killed run")
    )
    assert [e["action"] for e in _events(out, killed[0]) if e["event"] == "start"][:2] == ["ran", "resumed"]
    # the same command resumes them all: every run finished exactly once, with the local launcher's results
    said: list[str] = []
    runs = run_experiment(spec, output=out, launcher="ray", log=said.append, progress_interval=1)
    resumed = sorted("skipped-finished" if state[r.run_id] == "finished" else "finished" for r in runs)
    assert sorted(r.status for r in runs) == resumed, said
    _assert_each_finished_once(out, runs)
    assert any("runs done" in line for line in said)
    assert _report_content(out) == ref_report


@pytest.mark.slow
def test_submitit_local_executor_stops_on_sigint_and_resumes_to_local_results(tmp_path, local_reference):
    """``adarl experiment --launcher submitit`` (its local executor): SIGINT to the driver mid-run stops every
    running run after a checkpoint (through its stop file); the same command resumes them to the local launcher's
    results, each finished once. (Not a Ctrl-C to the whole group: submitit's local controller then kills its jobs a
    second later, and the runs resume from their last complete checkpoint instead.)"""
    pytest.importorskip("submitit")
    _, ref_report = local_reference
    out, spec = tmp_path / "exp", _spec(tmp_path)
    cmd = _experiment_cli(spec, out, "--launcher", "submitit", "--submitit-cluster", "local")
    proc = subprocess.Popen(
        cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    state = _stopped_on_sigint(proc, out, (lambda: _checkpointed_mid_run(out), "checkpoint past frame 0"))
    again = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-3000:]
    runs = plan_runs(load_experiment(spec), out)
    _assert_each_finished_once(out, runs)
    assert f"{sum(s != 'finished' for s in state.values())} finished" in again.stdout, again.stdout[-2000:]
    assert _report_content(out) == ref_report
    assert (out / "submitit").is_dir()


def _training_pids(marker: str) -> list[int]:
    """Processes whose command line runs ``adarl.cli`` and contains ``marker`` (Linux /proc)."""
    pids = []
    for d in Path("/proc").iterdir():
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError):
            continue
        if "adarl.cli" in cmd and marker in cmd:
            pids.append(int(d.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the training process through /proc")
def test_url_results_resume_on_a_fresh_scratch_and_match_local(tmp_path, local_reference, fake_s3):
    """Runs at a ``fakes3://`` URL (object-store semantics): one run's training is killed mid-run; the next session,
    on an empty scratch folder, downloads its latest checkpoint and finishes it, once; the report on the URL is the
    local launcher's."""
    _, ref_report = local_reference
    bucket = tmp_path / "bucket"
    url = f"fakes3://{bucket}/exp"
    spec = _spec(tmp_path)
    scratch_a, scratch_b = tmp_path / "scratch-a", tmp_path / "scratch-b"
    killed: list[str] = []

    def kill_one_training_mid_run():
        end = time.monotonic() + 240
        while time.monotonic() < end and not killed:
            for latest in sorted(bucket.glob("exp/*/checkpoints/LATEST")):
                try:
                    frames = json.loads(latest.read_text())["frames"]
                except (OSError, ValueError, KeyError):  # being written
                    continue
                run_id = latest.parent.parent.name
                pids = _training_pids(f"{scratch_a}/")
                pids = [p for p in pids if run_id in (Path(f"/proc/{p}/cmdline").read_bytes().decode(errors="replace"))]
                if 0 < frames < 600 and pids:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(run_id)
                    return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_one_training_mid_run, daemon=True)
    killer.start()
    said: list[str] = []
    with pytest.raises(AdaRLError, match="1 of 4 runs failed"):
        run_experiment(spec, output=url, scratch=scratch_a, report=False, log=said.append, progress_interval=1)
    killer.join()
    assert killed, "no training was killed mid-run"
    assert any("runs done" in line for line in said)
    assert not (bucket / "exp" / killed[0] / "summary.json").exists()
    # the killed run's log went to the URL; finished runs left nothing in the scratch folder
    assert (bucket / "exp" / f"{killed[0]}.log").is_file()
    assert sorted(p.name for p in scratch_a.glob("*/*") if p.is_dir()) == [killed[0]]

    runs = run_experiment(spec, output=url, scratch=scratch_b, log=said.append)  # e.g. another machine
    assert sorted(r.status for r in runs) == ["finished"] + ["skipped-finished"] * 3
    _assert_each_finished_once(url, runs)
    attempts = read_attempts(url, killed[0])
    assert [(e["event"], e["action"]) for e in attempts] == [
        ("start", "ran"),
        ("end", "ran"),
        ("start", "resumed"),
        ("end", "resumed"),
    ]
    assert attempts[2]["scratch"].startswith(str(scratch_b)) and attempts[1]["status"] == "failed"
    assert not (bucket / "exp" / f"{killed[0]}.log").exists()
    assert not [p for p in scratch_b.rglob("*") if p.is_file()]
    # the URL holds each run's latest checkpoint only, never a temporary name
    files = [p.relative_to(bucket).as_posix() for p in bucket.rglob("*") if p.is_file()]
    assert not [f for f in files if ".part-" in f or f.endswith(".tmp")]
    for r in runs:
        ckpts = bucket / "exp" / r.run_id / "checkpoints"
        frames = json.loads((ckpts / "LATEST").read_text())["frames"]
        assert sorted(p.name for p in ckpts.iterdir()) == [
            "LATEST",
            "best.pt",
            f"ckpt-{frames:012d}.pt",
            f"rb-{frames:012d}",
        ]
    # exact resume from the downloaded checkpoint: the same evaluations and table as the local launcher
    assert _report_content(bucket / "exp") == ref_report
    # adarl report on the URL, while nothing runs (it reads the URL through fsspec, writes the report there)
    from adarl.cli import main

    assert main(["report", url, "-o", f"{url}/report2"]) == 0
    with (bucket / "exp" / "report2" / "table.csv").open() as fh:
        assert repr(sorted(tuple(r.items()) for r in csv.DictReader(fh))) == ref_report["table"]
    with (bucket / "exp" / "report2" / "runs.csv").open() as fh:
        assert all(r["path"].startswith(f"{url}/") for r in csv.DictReader(fh))
    # finished runs are never re-run
    again = run_experiment(spec, output=url, scratch=scratch_b, report=False, log=lambda *_: None)
    assert sorted(r.status for r in again) == ["skipped-finished"] * 4


@pytest.mark.slow
def test_an_experiment_started_with_sigint_ignored_still_stops_on_a_ctrl_c_to_its_process_group(tmp_path):
    """`adarl experiment ... &` from a script inherits SIGINT ignored; a SIGINT must still stop it. Sent as a terminal
    sends Ctrl-C, to the whole process group: the training processes must not take it themselves (a second signal,
    the launcher's SIGTERM, would then stop them at once, without a checkpoint). Its running runs checkpoint and stop
    (``interrupted`` by the launcher's one SIGTERM), no other starts, and it exits 130 saying how to resume."""
    out = tmp_path / "exp"
    proc = subprocess.Popen(
        [sys.executable, "-m", "adarl.cli", "experiment", str(_spec(tmp_path)), "-o", str(out), "--no-live"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a shell's job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None and not list(out.glob("*/checkpoints/ckpt-*.pt")):
        time.sleep(0.2)
    assert proc.poll() is None, "the experiment ended before it could be interrupted"
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in its terminal
    try:
        _, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("SIGINT did not stop an experiment started with SIGINT ignored")
    assert proc.returncode == 128 + signal.SIGINT, err[-2000:]
    assert "experiment stopped on SIGINT" in err and "run the same `adarl experiment` command" in err, err[-2000:]
    assert _training_pids(str(out)) == []
    # it stopped its running runs after a checkpoint and started no other (before: every pending run still ran)
    runs = {r["run_id"]: r for r in json.loads((out / "experiment.json").read_text())["runs"]}
    state = {r: runs[r]["status"] for r in runs}
    started = {f.stem for f in (out / "attempts").glob("*.jsonl")}
    assert len(state) == 4 and 1 <= len(started) <= 2, (state, started)
    assert all(state[r] == "pending" for r in state if r not in started), state
    assert all(state[r] in ("interrupted", "finished") for r in started), state
    assert any(state[r] == "interrupted" for r in started), state
    for r in started:
        if state[r] == "interrupted":  # by the launcher's SIGTERM alone, after a checkpoint: not at once
            assert read_attempts(out, r)[-1]["status"] == "interrupted"
            # (exit 143 after its checkpoint; -15 when it had not yet set its handler, just started)
            assert "interrupted by SIGTERM (exit " in runs[r]["message"], runs[r]
            assert "stopped at once" not in (out / f"{r}.log").read_text()


def test_an_experiment_whose_output_reader_goes_away_stops_as_on_a_ctrl_c(tmp_path):
    """`adarl experiment ... | head` once `head` has exited (or a killed `tee`): the first progress line written to the
    closed pipe stops the experiment as a Unix tool stops on SIGPIPE, but as a Ctrl-C does here: each running run
    checkpoints and stops (``interrupted``), no other starts, the command says how to resume and exits 141. Before,
    the BrokenPipeError broke the launcher's loop, which killed the trainings at once, and ended in a traceback."""
    out = tmp_path / "exp"
    proc = subprocess.Popen(
        [sys.executable, "-m", "adarl.cli", "experiment", str(_spec(tmp_path)), "-o", str(out), "--no-live"]
        + ["--progress", "1"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        _wait_for(lambda: _checkpointed_mid_run(out), "checkpoint past frame 0", proc)
        proc.stdout.close()  # the reader goes away; the driver's next progress line hits the closed pipe
        err = proc.stderr.read()
        proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGPIPE, err[-2000:]
    assert "Traceback" not in err, err[-3000:]
    assert "experiment stopped on SIGPIPE" in err and "run the same `adarl experiment` command" in err, err[-2000:]
    assert _training_pids(str(out)) == []
    runs = {r["run_id"]: r for r in json.loads((out / "experiment.json").read_text())["runs"]}
    state = {r: runs[r]["status"] for r in runs}
    assert "interrupted" in state.values() and set(state.values()) <= {"interrupted", "pending", "finished"}, state
    for r, status in state.items():
        if status == "interrupted":  # after a checkpoint, by the launcher's one SIGTERM: not at once
            assert "stopped at once" not in (out / f"{r}.log").read_text()


def test_progress_counts_the_frames_of_runs_that_have_not_started(tmp_path):
    """0/4 runs done must not read as most of the frames: a pending run has no recipe.yaml yet, but its planned
    budget (known once its recipe validated) counts towards the total."""
    from adarl.experiments.orchestrate import _check_recipes

    spec = tmp_path / "s.yaml"
    spec.write_text(
        "kind: experiment\nname: s\nrecipe: quickstart\nseeds: [0, 1, 2, 3]\n"
        "overrides: [collector.total_frames=1000, collector.init_random_frames=100]\n"
    )
    runs = plan_runs(load_experiment(spec), tmp_path / "out")
    _check_recipes(runs)
    assert [r.total_frames for r in runs] == [1000] * 4
    first = Path(runs[0].path)
    (first / "metrics" / "scalars" / "train").mkdir(parents=True)
    (first / "recipe.yaml").write_text("collector: {total_frames: 1000}\n")
    (first / "metrics" / "scalars" / "train" / "updates.csv").write_text("800,700\n")
    board = ProgressBoard(runs)
    board.running.add(runs[0].run_id)
    _, totals = board.snapshot()
    assert (totals.done_frames, totals.all_frames, totals.n_done, totals.n) == (800, 4000, 0, 4)
    assert "0/4 runs done, 20% of frames" in totals.line(10)


def test_a_run_stopped_by_sigterm_from_outside_is_interrupted_not_failed_and_resumes(tmp_path):
    """A training process sent SIGTERM by someone else (a session's end, a scheduler) checkpoints and exits 143: the
    experiment says the run was interrupted and resumes on the next call, not that it failed; the attempt log says
    the same. The next `adarl experiment` resumes it (never starts it again) and finishes it."""
    spec = tmp_path / "one.yaml"
    spec.write_text(
        yaml.safe_dump({"kind": "experiment", "name": "one", "recipe": "quickstart", "overrides": TINY, "seeds": [0]})
    )
    out = tmp_path / "exp"
    sent: list[int] = []
    done = threading.Event()

    def sigterm_the_training_after_its_first_checkpoint():
        while not done.is_set() and not sent:
            frames = [int(c.stem.split("-")[1]) for c in out.glob("*/checkpoints/ckpt-*.pt")]
            if any(0 < f < 500 for f in frames):
                pids = _training_pids(str(out))
                if pids:
                    os.kill(pids[0], signal.SIGTERM)
                    sent.append(pids[0])
                    return
            time.sleep(0.05)

    sender = threading.Thread(target=sigterm_the_training_after_its_first_checkpoint, daemon=True)
    sender.start()
    try:
        with pytest.raises(AdaRLError, match="1 of 1 runs were interrupted by a signal and resume") as err:
            run_experiment(spec, output=out, report=False, log=lambda *_: None)
    finally:
        done.set()
        sender.join()
    assert sent, "no training was sent SIGTERM mid-run"
    assert "failed" not in str(err.value)
    (run_id,) = [p.name for p in out.iterdir() if p.is_dir() and p.name != "attempts"]
    state = json.loads((out / "experiment.json").read_text())
    assert [(r["run_id"], r["status"]) for r in state["runs"]] == [(run_id, "interrupted")]
    assert "interrupted by SIGTERM (exit 143)" in state["runs"][0]["message"]
    assert read_attempts(out, run_id)[-1]["status"] == "interrupted"

    runs = run_experiment(spec, output=out, report=False, log=lambda *_: None)
    assert [r.status for r in runs] == ["finished"]
    assert [(e["event"], e["action"]) for e in read_attempts(out, run_id)] == [
        ("start", "ran"),
        ("end", "ran"),
        ("start", "resumed"),
        ("end", "resumed"),
    ]


def test_an_exit_status_names_the_interrupting_signal_only_for_the_stop_signals():
    from adarl.experiments.execute import interrupting_signal

    assert interrupting_signal(128 + signal.SIGTERM) == signal.SIGTERM
    assert interrupting_signal(-signal.SIGTERM) == signal.SIGTERM
    assert interrupting_signal(128 + signal.SIGINT) == signal.SIGINT
    assert interrupting_signal(-signal.SIGINT) == signal.SIGINT
    assert interrupting_signal(128 + signal.SIGHUP) == signal.SIGHUP  # a closed session: checkpointed (issue 46.8)
    for other in (0, 1, 2, -signal.SIGKILL, 128 + signal.SIGKILL, None):  # SIGKILL: the OOM killer's, a failure
        assert interrupting_signal(other) is None


def test_an_interrupted_wait_stops_the_training_with_one_sigterm_and_waits_for_it():
    """A job or task process interrupted while its run trains (``KeyboardInterrupt``: submitit's cancel, ``ray.cancel``,
    a Ctrl-C to its group) sends the training one SIGTERM and waits for it to end (after its checkpoint), then is
    interrupted: it does not kill it mid-batch."""
    from adarl.experiments.execute import _wait

    handler = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGTERM, lambda *_: (print('checkpointed', flush=True), sys.exit(143)))\n"
        "print('ready', flush=True)\n"
        "while True: time.sleep(0.05)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", handler], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"

    def interrupted():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _wait(proc, interrupted)
    assert proc.returncode == 143 and proc.stdout.read().strip() == "checkpointed"


def test_a_stop_request_reaches_a_run_in_a_folder_and_at_a_url(tmp_path, fake_s3):
    """The Ray and submitit launchers stop a run through a file beside it, in a shared folder or in the same store
    as a URL output; withdrawn, it no longer stops it."""
    from adarl.experiments.execute import StopAsked, clear_stop, request_stop

    for path in (str(tmp_path / "exp" / "run"), f"fakes3://{tmp_path}/bucket/exp/run"):
        watch = StopAsked(path)
        assert not watch()
        request_stop(path)
        assert watch()
        clear_stop(path)
        assert not watch()
        clear_stop(path)  # withdrawing twice is fine
    assert (tmp_path / "bucket" / "exp").is_dir() and not list((tmp_path / "bucket" / "exp").iterdir())


def test_a_dry_run_names_the_runs_it_would_resume_and_from_which_frames(tmp_path):
    """`adarl experiment --dry-run` of a folder with an interrupted run: that run is listed as resumable from its
    latest checkpoint's frames, the others as pending; nothing is run or written."""
    spec = _spec(tmp_path)
    out = tmp_path / "exp"
    planned = plan_runs(load_experiment(spec), out)
    ckpts = Path(planned[1].path) / "checkpoints"
    ckpts.mkdir(parents=True)
    for frames in (100, 350):
        (ckpts / f"ckpt-{frames:012d}.pt").write_bytes(b"")
    said: list[str] = []
    runs = run_experiment(spec, output=out, dry_run=True, log=said.append)
    assert [r.status for r in runs] == ["pending"] * 4
    rows = [line.split() for line in said if line.startswith("  ")]
    assert [(row[0], row[1].rstrip(":")) for row in rows] == [
        ("resumable" if r.run_id == planned[1].run_id else "pending", r.run_id) for r in planned
    ]
    (line,) = [line for line in said if "resumable" in line]
    assert line.endswith("(resumes from its checkpoint at 350 frames)")
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == [
        f"{planned[1].run_id}/checkpoints/ckpt-{f:012d}.pt" for f in (100, 350)
    ]


def test_an_experiment_stopped_at_once_says_how_to_resume_it(tmp_path, monkeypatch, capsys):
    """A KeyboardInterrupt out of the experiment (a second signal on Ray or submitit) is one line that names the
    command that resumes it, exit 130, not `adarl resume RUN_DIR` of a single run."""
    import adarl.experiments.orchestrate as orchestrate
    from adarl.cli import main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(orchestrate, "run_experiment", interrupted)
    assert main(["experiment", str(_spec(tmp_path)), "-o", str(tmp_path / "out"), "--no-live"]) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run the same `adarl experiment` command to resume it" in err, err


def _hold_kernel_lock(lock: Path) -> subprocess.Popen:
    """Another process holding the kernel lock on ``lock`` as adarl does (flock, and who holds it in the file),
    until it is killed; started in milliseconds (no adarl import)."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, json, os, socket, sys\n"
            f"fd = os.open({str(lock)!r}, os.O_RDWR | os.O_CREAT, 0o644)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
            "os.write(fd, json.dumps({'pid': os.getpid(), 'host': socket.gethostname(), 'since': 'now'}).encode())\n"
            "print('held', flush=True); sys.stdin.read()\n",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    return holder


@pytest.mark.parametrize("command", ["experiment", "tune"])
def test_a_second_driver_on_the_same_output_is_refused_and_writes_nothing(tmp_path, command):
    """Two `adarl experiment` (or `adarl tune`) on one output folder would start the same pending runs, and the second
    clears the folder of a run the first had just started: the second is refused, naming who holds the folder, before
    it writes anything. The lock is the kernel's: once its holder is killed (kill -9), the folder is free."""
    out = tmp_path / "exp"
    out.mkdir()
    lock = out / (".adarl-experiment.lock" if command == "experiment" else ".tune.lock")
    holder = _hold_kernel_lock(lock)
    try:
        with pytest.raises(AdaRLError, match=rf"another `adarl {command}` is running on .*\(pid {holder.pid} on "):
            if command == "experiment":
                run_experiment(_spec(tmp_path), output=out, log=lambda *_: None)
            else:
                from adarl.experiments.tune import run_tune

                run_tune(REPO / "recipes" / "tune" / "cartpole_beta.yaml", output=out, log=lambda *_: None)
        assert sorted(p.name for p in out.iterdir()) == [lock.name]  # nothing written
    finally:
        holder.kill()
        holder.wait()
    from adarl.runtime.run_folder.run_dir import exclusive_lock

    with exclusive_lock(lock, RuntimeError):  # a killed holder holds it no more
        pass


def test_a_run_folder_another_process_trains_in_is_never_cleared(tmp_path):
    """A run folder without a checkpoint is cleared before its run starts (nothing to keep), but not while another
    process trains in it (its first checkpoint not written yet): the run is not started, and says why."""
    from adarl.experiments.execute import execute_run
    from adarl.experiments.spec import PlannedRun

    folder = tmp_path / "exp" / "run"
    folder.mkdir(parents=True)
    (folder / "recipe.yaml").write_text("written by the run that trains here\n")
    holder = _hold_kernel_lock(folder / ".adarl.lock")  # a run training there, its first checkpoint not yet written
    try:
        run = PlannedRun("run", {}, 0, "quickstart", [], str(folder))
        assert execute_run(run, 1).status == "failed"
        assert f"is in use by another process (pid {holder.pid} on " in run.message, run.message
        assert (folder / "recipe.yaml").read_text() == "written by the run that trains here\n"
        assert not (tmp_path / "exp" / "attempts").exists()  # not started
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.slow
def test_an_output_folder_deleted_mid_experiment_stops_it_in_one_line_and_is_not_recreated(tmp_path):
    """`rm -rf` of the output folder while `adarl experiment` runs: the runs are stopped, no queued run starts, the
    folder is not recreated half-filled, and the command says so in one line (before: a FileNotFoundError
    traceback, after the queued runs had trained in a recreated folder)."""
    import shutil

    out = tmp_path / "exp"
    proc = subprocess.Popen(
        _experiment_cli(_spec(tmp_path), out), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        _wait_for(lambda: _checkpointed_mid_run(out), "checkpoint past frame 0", proc)
        while out.exists():  # (files written while it is removed: again)
            shutil.rmtree(out, ignore_errors=True)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1, err[-3000:]
    assert "was deleted or moved while the experiment ran" in err and "Traceback" not in err, err[-3000:]
    assert not out.exists() and _training_pids(str(out)) == []


# ------------------------------------------------------------------------------------------ launchers that cannot start


def _one_line(proc: subprocess.CompletedProcess, status: int, *words: str) -> str:
    assert proc.returncode == status and "Traceback" not in proc.stderr, (proc.returncode, proc.stderr[-3000:])
    [line] = [line for line in proc.stderr.splitlines() if line.startswith("adarl: error:")]
    assert all(w in line for w in words), line
    return line


def test_a_ray_address_nothing_answers_at_is_refused_in_one_line_before_ray_retries(tmp_path):
    """Issue 46.8: `--launcher ray --ray-address 127.0.0.1:1` retried for minutes with no end (Ray's own retries):
    refused in one line naming the address, within the launcher's connect timeout."""
    pytest.importorskip("ray")
    proc = subprocess.run(
        _experiment_cli(_spec(tmp_path), tmp_path / "out", "--launcher", "ray", "--ray-address", "127.0.0.1:1"),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,  # a guard against a hang; what is checked is who refused it
    )
    # refused by our own connect check (its words), so Ray's retries never started: an event, not a clock
    _one_line(proc, 1, "cannot reach the Ray cluster at '127.0.0.1:1'", "(within 10 s)")


def test_a_ray_address_that_never_answers_is_refused_after_the_connect_timeout(monkeypatch):
    """The same for an address that never answers (a dropped packet, a firewall): bounded by ``connect_timeout_s``."""
    pytest.importorskip("ray")
    import socket

    from adarl.experiments.launchers import RayLauncher

    asked: list[float | None] = []

    def no_answer(address, timeout=None):  # as a connect that hangs until its timeout
        asked.append(timeout)
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", no_answer)
    with pytest.raises(
        AdaRLError, match=r"cannot reach the Ray cluster at '127.0.0.1:6379': no answer \(within 0.5 s\)"
    ):
        with RayLauncher("127.0.0.1:6379", connect_timeout_s=0.5).session():
            pass
    assert asked == [0.5]  # one connect, bounded by the timeout, no retries (events, not a clock)


def test_a_ray_client_address_without_ray_client_is_one_line_and_writes_nothing(tmp_path, monkeypatch):
    """Issue 46.8: a `ray://` address without `ray[client]` gave Ray's ValueError as a traceback: bad input, one line
    naming the missing extra, before the experiment writes anything."""
    pytest.importorskip("ray")
    import importlib.util

    from adarl.errors import MissingExtraError
    from adarl.experiments.launchers import RayLauncher

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "grpc" else real(name, *a))
    with pytest.raises(
        MissingExtraError, match=r"'ray://127.0.0.1:1' is a Ray Client address .* pip install 'ray\[client\]'"
    ):
        RayLauncher("ray://127.0.0.1:1")
    monkeypatch.undo()
    if importlib.util.find_spec("grpc") is None:  # this machine lacks it too: the command says so
        out = tmp_path / "out"
        proc = subprocess.run(
            _experiment_cli(_spec(tmp_path), out, "--launcher", "ray", "--ray-address", "ray://127.0.0.1:1"),
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=300,
        )
        _one_line(proc, 2, "ray://127.0.0.1:1", "pip install 'ray[client]'")
        assert not out.exists()


@pytest.mark.parametrize("present", [["sbatch"], []], ids=["sbatch without srun", "neither"])
def test_submitit_on_slurm_without_its_executables_is_one_line_naming_them(tmp_path, present):
    """Issue 46.8: `--launcher submitit --submitit-cluster slurm` on a machine without `srun` gave submitit's
    RuntimeError as a traceback (without `sbatch`: a FileNotFoundError at the first submission)."""
    pytest.importorskip("submitit")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for exe in present:  # a PATH with only these of SLURM's executables
        (bin_dir / exe).write_text("#!/bin/sh\nexit 1\n")
        (bin_dir / exe).chmod(0o755)
    proc = subprocess.run(
        _experiment_cli(_spec(tmp_path), tmp_path / "out", "--launcher", "submitit", "--submitit-cluster", "slurm"),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PATH": str(bin_dir)},
    )
    missing = "srun" if present else "sbatch and srun"
    _one_line(proc, 1, f"slurm cluster needs {missing}", "--submitit-cluster local")
