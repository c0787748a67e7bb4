"""One run of an experiment, wherever a launcher puts it: :func:`execute_run`.

It starts ``adarl run`` (or ``adarl resume`` when the run folder has a checkpoint) in a child process that dies with
its launcher process, so a worker lost mid-run is retried from the run's last checkpoint and a finished run is never
started again; each start and end is recorded in ``<output>/attempts/``. A run at an fsspec URL trains in a local
scratch folder that is uploaded after each checkpoint (:class:`~adarl.runtime.run_folder.results.RunMirror`). This
module is a
leaf of the experiment tooling: it knows a :class:`~adarl.experiments.spec.PlannedRun` and the run folder, nothing of
launchers, progress boards or reports.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import yaml

from adarl.errors import AdaRLError
from adarl.experiments.spec import PlannedRun
from adarl.runtime.config import load_recipe
from adarl.runtime.fingerprint import differences
from adarl.runtime.run_folder.results import (
    LATEST,
    SYNC_INTERVAL_S,
    RunMirror,
    exists,
    filesystem,
    is_url,
    join,
    read_text,
    scratch_folder,
    write_atomic,
)
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = [
    "execute_run",
    "settled_before_start",
    "run_is_finished",
    "holds_training",
    "read_attempts",
    "ATTEMPTS_DIR",
    "stop_file",
    "StopAsked",
    "request_stop",
    "clear_stop",
    "OutputFolderGone",
    "start_training",
    "prepare_url_run",
    "push_when_due",
    "wait_uploading",
    "settle_url_run",
]

ATTEMPTS_DIR = "attempts"  # <output>/attempts/<run id>.jsonl: one line per start and end of a run, by any launcher

_LIVE: dict[subprocess.Popen, int | None] = {}  # training processes this process waits for -> the signal sent
_LIVE_LOCK = threading.Lock()


class OutputFolderGone(AdaRLError):
    """The experiment's output folder was deleted or moved while it ran: its runs had nowhere left to write, and
    nothing is recreated there (a half-filled folder would pass for the experiment)."""

    def __init__(self, output: str | os.PathLike) -> None:
        super().__init__(
            f"output folder {str(output)!r} was deleted or moved while the experiment ran: its runs were stopped and "
            f"nothing was recreated there. Run the command again to start afresh, or, if it was moved, with -o and "
            f"the new place to resume its runs there"
        )


def signal_live_trainings(sig: int) -> int:
    """Send ``sig`` to every training process this process is waiting for that has not had it yet; returns how many
    got it. SIGTERM: each checkpoints after its batch and exits (``interrupted``, resumable); SIGKILL: at once, each
    keeping its last checkpoint. A launcher stopping on a signal calls it until its runs have ended."""
    with _LIVE_LOCK:
        todo = [proc for proc, sent in _LIVE.items() if sent != sig]
        for proc in todo:
            _LIVE[proc] = sig
    for proc in todo:
        with contextlib.suppress(OSError):
            proc.send_signal(sig)
    return len(todo)


@contextlib.contextmanager
def _live(proc: subprocess.Popen):
    """``proc`` is one of :func:`signal_live_trainings`'s while the block runs; yields a list that holds, after it,
    the signal this process sent it (None: none)."""
    sent: list[int | None] = [None]
    with _LIVE_LOCK:
        _LIVE[proc] = None
    try:
        yield sent
    finally:
        with _LIVE_LOCK:
            sent[0] = _LIVE.pop(proc, None)


def stop_file(path: str | os.PathLike) -> Path:
    """The file that asks the run in the folder ``path`` to stop: ``.<name>.stop`` beside the folder (not in it: a
    run's first start clears its folder, and ``adarl run`` refuses a folder holding files it did not write)."""
    p = Path(path)
    return p.parent / f".{p.name}.stop"


def _stop_url(url: str) -> str:
    """:func:`stop_file` of a run at an fsspec URL: ``.<name>.stop`` beside it, in the same store."""
    parent, name = url.rstrip("/").rsplit("/", 1)
    return join(parent, f".{name}.stop")


def request_stop(path: str | os.PathLike) -> None:
    """Ask the run at ``path`` (a folder, or an fsspec URL) to stop (it checkpoints first) from any machine that sees
    it: the :class:`StopAsked` watcher of the :func:`execute_run` running it (on a Ray worker, in a SLURM job) sends the
    training SIGTERM within :data:`WATCH_POLL_S` seconds. ``adarl tune`` stops a pruned trial so, and the Ray and
    submitit launchers stop an experiment's runs so on its first SIGINT/SIGTERM."""
    if is_url(path):
        write_atomic(_stop_url(str(path)), f"{os.getpid()}\n")
        return
    f = stop_file(path)
    f.parent.mkdir(parents=True, exist_ok=True)
    f.write_text(f"{os.getpid()}\n")


def clear_stop(path: str | os.PathLike) -> None:
    """Withdraw a :func:`request_stop` (before the run is started again)."""
    if is_url(path):
        fs, rpath = filesystem(_stop_url(str(path)))
        with contextlib.suppress(FileNotFoundError):
            fs.rm(rpath)
        return
    stop_file(path).unlink(missing_ok=True)


class StopAsked:
    """A picklable ``watch`` for :func:`execute_run`: true once :func:`request_stop` was called on the run."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = str(path)

    def __call__(self) -> bool:
        if is_url(self.path):
            fs, rpath = filesystem(_stop_url(self.path))
            return fs.exists(rpath)
        return stop_file(self.path).exists()


def run_is_finished(path: str | os.PathLike) -> bool:
    """A run folder (or URL) whose summary shows its whole frame budget spent, or a callback's early stop that
    still holds under its recipe.yaml (docs/callbacks.md)."""
    if is_url(path):
        summary, recipe = read_text(join(path, "summary.json")), read_text(join(path, "recipe.yaml"))
        if summary is None or recipe is None:
            return False
    else:
        p = Path(path)
        if not ((p / "summary.json").is_file() and (p / "recipe.yaml").is_file()):
            return False
        summary, recipe = (p / "summary.json").read_text(), (p / "recipe.yaml").read_text()
    try:
        done, resolved = json.loads(summary), yaml.safe_load(recipe)
        total = int(resolved["collector"]["total_frames"])
        stop = done.get("stopped_early")
        if isinstance(stop, dict) and stop.get("total_frames") == total:
            return stop.get("callbacks") == (resolved.get("callbacks") or [])
        return int(done.get("frames", -1)) >= total
    except (ValueError, KeyError, TypeError, AttributeError, yaml.YAMLError, json.JSONDecodeError):
        return False


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "adarl.cli", *args]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: the training process gets SIGKILL when its launcher process dies (a lost Ray worker, a killed job),
    so a retried run never races an orphan writing the same folder.

    The training process also runs in its own process group (``process_group=0``): a Ctrl-C in the terminal goes to
    the launcher's group only, and the launcher passes one SIGTERM on. Were it in the launcher's group it would get
    both, and a second signal stops a run at once, without its checkpoint."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _make_below(run: PlannedRun, folder: Path) -> None:
    """Create ``folder`` (and its parents) below the run's output folder, never the output folder itself: once that
    was deleted or moved, :class:`OutputFolderGone` (nothing is recreated half-filled)."""
    root = Path(run.output) if run.output is not None and not is_url(run.output) else None
    if root is None or not folder.is_relative_to(root):
        folder.mkdir(parents=True, exist_ok=True)
        return
    here = root
    try:
        for part in folder.relative_to(root).parts:
            here = here / part
            here.mkdir(exist_ok=True)
        if not root.is_dir():
            raise FileNotFoundError(root)
    except FileNotFoundError:
        raise OutputFolderGone(root) from None


def _record_attempt(run: PlannedRun, **event) -> None:
    if is_url(run.path):  # object stores cannot append: one small file per event, named so that they sort in order
        event = {"time": time.time(), "host": socket.gethostname(), "pid": os.getpid(), **event}
        name = f"{time.time_ns():020d}-{event['event']}-{uuid.uuid4().hex[:6]}.json"
        write_atomic(join(run.path.rsplit("/", 1)[0], ATTEMPTS_DIR, run.run_id, name), json.dumps(event) + "\n")
        return
    folder = Path(run.path).parent / ATTEMPTS_DIR
    _make_below(run, folder)
    event = {"time": time.time(), "host": socket.gethostname(), "pid": os.getpid(), **event}
    with (folder / f"{run.run_id}.jsonl").open("a") as fh:
        fh.write(json.dumps(event) + "\n")


def read_attempts(output: str | os.PathLike, run_id: str) -> list[dict]:
    """The start/end events of a run, in order (``event``: start | end; ``action``: ran | resumed | uploaded;
    ``pid``...). At a URL they are ``attempts/<run id>/*.json``, one file per event."""
    if is_url(output):
        fs, folder = filesystem(join(output, ATTEMPTS_DIR, run_id))
        try:
            names = sorted(fs.ls(folder, detail=False))
        except FileNotFoundError:
            return []
        events = []
        for name in names:
            if name.endswith(".json"):
                try:
                    events.append(json.loads(fs.cat_file(name)))
                except (FileNotFoundError, ValueError):  # being written (local-like filesystems)
                    continue
        return sorted(events, key=lambda e: e.get("time", 0))
    f = Path(output) / ATTEMPTS_DIR / f"{run_id}.jsonl"
    if not f.is_file():
        return []
    return [json.loads(line) for line in f.read_text().splitlines() if line.strip()]


def holds_training(path: str) -> bool:
    """Whether a run folder holds training to reuse, made from a recipe it records: finished, or a checkpoint to
    resume from beside its recipe.yaml. (A folder without either is a start that never checkpointed: nothing to
    keep, it starts afresh; one without a recipe.yaml cannot be resumed, and its attempt says so.)"""
    if run_is_finished(path):
        return True
    if is_url(path):
        return exists(join(path, "recipe.yaml")) and exists(join(path, "checkpoints", LATEST))
    return (Path(path) / "recipe.yaml").is_file() and RunDir(path).latest_checkpoint_frames() is not None


def settled_before_start(run: PlannedRun) -> bool:
    """Whether a worker must not train ``run`` (its status then set): its folder holds training made from another
    recipe (``changed``), or it has finished (``skipped-finished``). The driver placed it so; a worker checks again:
    its files may be another's, or a retried task's first try finished before its worker was lost."""
    if holds_training(run.path):
        diff = differences(run.path, load_recipe(run.recipe, run.overrides))
        if diff:
            run.status, run.message = "changed", f"made from another recipe ({run.path}): " + "; ".join(diff)
            return True
    if run_is_finished(run.path):
        run.status, run.message = "skipped-finished", "already finished"
        return True
    return False


def execute_run(run: PlannedRun, threads: int | None, watch: Callable[[], bool] | None = None) -> PlannedRun:
    """Run (or resume, when its folder has a checkpoint) one run with the ``adarl`` command; sets its status.

    What every launcher executes, wherever it runs; a finished run is left alone (``skipped-finished``). A run at a
    URL trains in a local scratch folder copied to the URL (:func:`_execute_at_url`).

    ``watch``: called every :data:`WATCH_POLL_S` seconds while the run trains; when it returns True the run is sent
    SIGTERM (it checkpoints and stops, resumable) and its status is ``stopped`` (``adarl tune`` prunes a trial so, on
    the evaluations the run has written; a launcher stops its runs so on a signal). A run whose ``watch`` is already
    true when it would start is not started: its status stays ``pending``."""
    if settled_before_start(run):
        return run
    if watch is not None and watch():  # its launcher stopped before this worker started it
        run.status, run.message = "pending", "asked to stop before it started"
        return run
    if is_url(run.path):
        return _execute_at_url(run, threads, watch)
    path = Path(run.path)
    if RunDir(path).latest_checkpoint_frames() is not None:
        cmd, action = _cli("resume", str(path), "--quiet"), "resumed"
    else:
        if path.exists():  # a start that never checkpointed: nothing to keep, unless a process trains in it now
            try:
                RunDir(path).lock()
            except AdaRLError as err:  # (another driver, an `adarl run`/`resume` by hand): left alone
                run.status, run.message = "failed", f"not started: {err}"
                return run
            shutil.rmtree(path)
            RunDir(path).unlock()
        cmd, action = _cli("run", run.recipe, *run.overrides, "-o", str(path), "--quiet"), "ran"
    _make_below(run, path.parent)
    log = path.parent / f"{run.run_id}.log"
    _record_attempt(run, event="start", action=action)
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = start_training(cmd, fh, threads)
        with _live(proc) as sent:
            try:
                stopped, interrupted = _wait(proc, watch), None
            except KeyboardInterrupt as err:  # its worker was interrupted: the training has stopped (_end_training)
                stopped, interrupted = False, err
    run.wall_time_s = time.perf_counter() - start
    if not Path(run.output or path.parent).is_dir():  # deleted or moved under the run (which stopped with it)
        raise OutputFolderGone(run.output or path.parent)
    if _ended_finished(proc.returncode, path):
        run.status, run.message = "finished", action
        log.unlink(missing_ok=True)
    elif stopped:
        run.status, run.message = (
            "stopped",
            f"stopped by its watcher (exit {proc.returncode}); {_resumes(run)} (log: {log})",
        )
    else:
        tail = log.read_text().strip().splitlines()[-1:] if log.is_file() else []
        _set_unfinished(run, proc.returncode, tail, log, sent=sent[0])
    _record_attempt(run, event="end", action=action, status=run.status)
    if interrupted is not None:  # recorded: now the caller (a job, a task, adarl tune) is interrupted as it asked
        raise interrupted
    return run


#: The signals a training checkpoints and stops on (:mod:`adarl.runtime.signals`): a run ended by one was
#: interrupted from outside (a session's end, a scheduler, Ctrl-C), not broken; it resumes exactly when asked.
INTERRUPTING_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def interrupting_signal(returncode: int | None) -> signal.Signals | None:
    """The signal of :data:`INTERRUPTING_SIGNALS` a training process's exit status says stopped it: ``128 + n``
    (``adarl run`` after its checkpoint) or ``-n`` (killed by it before its handler was set); None otherwise."""
    for sig in INTERRUPTING_SIGNALS:
        if returncode in (128 + int(sig), -int(sig)):
            return sig
    return None


def _ended_finished(returncode: int | None, path) -> bool:
    """Whether a training process that exited so finished its run: exit 0, or a stop signal received after its last
    batch (it writes its summary and report first, then exits with the signal's status) with the budget spent."""
    return (returncode == 0 or interrupting_signal(returncode) is not None) and run_is_finished(path)


def _resumes(run: PlannedRun) -> str:
    """How an unfinished run goes on: from its last checkpoint, or afresh when it had none (a local folder)."""
    fresh = not is_url(run.path) and RunDir(run.path).latest_checkpoint_frames() is None
    return "it had no checkpoint yet, so it starts afresh" if fresh else "resumes from its last checkpoint"


def _set_unfinished(run: PlannedRun, returncode: int | None, tail: list[str], log, sent: int | None = None) -> None:
    """Status of a run whose training ended before its budget: ``interrupted`` when a signal of
    :data:`INTERRUPTING_SIGNALS` stopped it (resumable: the next ``adarl experiment`` resumes it from its last
    checkpoint) or when this process killed it (``sent``: a launcher told to stop at once), ``failed`` otherwise
    (another SIGKILL included: the out-of-memory killer sends it, and would again)."""
    sig = interrupting_signal(returncode)
    resumes = _resumes(run)
    if sent == signal.SIGKILL and returncode == -signal.SIGKILL:
        run.status = "interrupted"
        run.message = f"killed at once by its launcher (a second signal); {resumes} (log: {log})"
    elif sig is not None:
        run.status = "interrupted"
        run.message = (
            f"interrupted by {sig.name} (exit {returncode}); {resumes} when the experiment is run again (log: {log})"
        )
    else:
        run.status, run.message = "failed", f"exit {returncode}: {' '.join(tail)} (log: {log})"


WATCH_POLL_S = 0.25  # how often a watched run's watcher is asked whether to stop it (a tune trial waits on it)


def _wait(proc: subprocess.Popen, watch: Callable[[], bool] | None) -> bool:
    """Wait for the training process; with a ``watch``, ask it now and then and send SIGTERM when it says stop.
    Returns whether it was stopped so. Interrupted (``KeyboardInterrupt``), it stops the training first
    (:func:`_end_training`), then raises."""
    stopped = False
    try:
        while True:
            try:
                proc.wait(timeout=WATCH_POLL_S if watch is not None and not stopped else None)
                return stopped
            except subprocess.TimeoutExpired:
                pass
            if watch():
                stopped = True
                proc.send_signal(signal.SIGTERM)  # the trainer checkpoints after its batch and exits
    except BaseException as err:
        _end_training(proc, err, sigterm_sent=stopped)
        raise


def _end_training(proc: subprocess.Popen, err: BaseException, *, sigterm_sent: bool) -> None:
    """The training process of a waiting thread that was interrupted. ``KeyboardInterrupt`` (a Ctrl-C to a submitit
    job's process group, its cancel, ``ray.cancel``): it is sent SIGTERM (once) and waited for, so it checkpoints after
    its batch first; a second interrupt, or any other exception, kills it at once (it keeps its last checkpoint)."""
    if isinstance(err, KeyboardInterrupt):
        try:
            if not sigterm_sent:
                proc.send_signal(signal.SIGTERM)
            proc.wait()
            return
        except BaseException:  # noqa: BLE001 - interrupted again: at once, below
            pass
    proc.kill()
    proc.wait()


def _train_env(threads: int | None) -> dict:
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    return env


_POLL_S = 1.0  # how often a URL run's scratch folder is checked for a new checkpoint to upload


def start_training(cmd: list[str], log, threads: int | None) -> subprocess.Popen:
    """A training process (``adarl run`` / ``resume``) writing to the open file ``log``, in its own process group (a
    terminal's Ctrl-C reaches its launcher alone, which stops it once: :func:`_wait`), dying with this process."""
    return subprocess.Popen(
        cmd,
        stdout=log,
        stderr=subprocess.STDOUT,
        env=_train_env(threads),
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
        process_group=0,
    )


def wait_uploading(
    proc: subprocess.Popen, watch: Callable[[], bool] | None, uploads: list[tuple[RunMirror, str]], log
) -> tuple[int | None, bool, KeyboardInterrupt | None]:
    """Wait for a training process whose runs are at URLs, uploading each ``(mirror, url)`` when due
    (:func:`push_when_due`) and sending SIGTERM when ``watch`` says stop. Returns ``(exit status, stopped by the
    watch, the KeyboardInterrupt to raise once the runs are settled)``: interrupted, the training is stopped first
    (:func:`_end_training`: it checkpoints, then everything is uploaded by the caller); any other error is raised."""
    stopped = False
    try:
        while True:
            try:
                return proc.wait(timeout=_POLL_S), stopped, None
            except subprocess.TimeoutExpired:
                pass
            if watch is not None and not stopped and watch():
                stopped = True
                proc.send_signal(signal.SIGTERM)  # the trainer checkpoints after its batch; uploaded after
            for mirror, url in uploads:
                push_when_due(mirror, log, url)
    except BaseException as err:
        _end_training(proc, err, sigterm_sent=stopped)
        if not isinstance(err, KeyboardInterrupt):
            raise
        return proc.returncode, stopped, err


def prepare_url_run(run: PlannedRun) -> tuple[Path, RunMirror, str] | None:
    """Before an attempt at a run at a URL: its scratch folder made to hold the run's latest state (downloaded when
    it lacks the URL's latest checkpoint) and how the attempt goes on: ``"ran"`` (no checkpoint at the URL: a fresh
    start), ``"resumed"``, or ``"uploaded"`` (finished here, but the worker was lost before the upload ended).
    Returns ``(scratch folder, mirror, action)``, or None with the run ``failed`` when the URL cannot be read."""
    local = scratch_folder(run.path, run.run_id, run.scratch)
    local.parent.mkdir(parents=True, exist_ok=True)
    mirror = RunMirror(local, run.path)
    try:
        state = mirror.prepare()
    except Exception as err:  # noqa: BLE001 - e.g. the store does not answer: this attempt fails, others go on
        run.status, run.message = "failed", f"could not read {run.path}: {type(err).__name__}: {err}"
        return None
    action = "ran" if state == "fresh" else "uploaded" if run_is_finished(local) else "resumed"
    return local, mirror, action


def push_when_due(mirror: RunMirror, log, url: str) -> None:
    """While a URL run trains: upload after each new checkpoint (and every :data:`SYNC_INTERVAL_S` for the metrics);
    a failed upload is written to the training's ``log`` (an open file) and retried at the next."""
    if mirror.has_new_checkpoint() or time.monotonic() - mirror.last_push >= SYNC_INTERVAL_S:
        try:
            mirror.push()
        except Exception as err:  # noqa: BLE001 - retried at the next checkpoint; the run goes on
            log.write(f"adarl: upload to {url} failed (retrying later): {err}\n")
            log.flush()


def settle_url_run(
    run: PlannedRun,
    local: Path,
    mirror: RunMirror,
    finished_here: bool,
    returncode: int | None,
    log: Path,
    done: str,
    *,
    stopped: bool = False,
    sent: int | None = None,
) -> None:
    """After an attempt at a run at a URL: the last upload (everything, ``summary.json`` last, when it finished in
    ``local``) and the run's status (``finished`` with the message ``done`` once the URL holds it); an unfinished
    run's ``log`` goes to the URL beside it (``<run id>.log``), a finished one leaves nothing in the scratch folder."""
    remote_log = join(run.path.rsplit("/", 1)[0], f"{run.run_id}.log")
    try:
        mirror.push(final=finished_here)
        upload_error = None
    except Exception as err:  # noqa: BLE001 - reported below; the scratch folder is kept for a retry
        upload_error = err
    if finished_here and upload_error is None and run_is_finished(run.path):
        run.status, run.message = "finished", done
        mirror.clean()
        fs, rpath = filesystem(remote_log)
        if fs.exists(rpath):  # the log of an earlier failed attempt
            fs.rm(rpath)
    elif finished_here:
        why = upload_error or "its summary.json is not readable there"
        run.status, run.message = "failed", f"finished in {local} but the upload to {run.path} failed: {why}"
    else:
        tail = log.read_text().strip().splitlines()[-1:] if log.is_file() else []
        try:
            write_atomic(remote_log, log.read_text() if log.is_file() else "")
            where = remote_log
        except Exception:  # noqa: BLE001 - the local log is still there
            where = str(log)
        if stopped:
            run.status, run.message = "stopped", f"stopped by its watcher (exit {returncode}); resumable (log: {where})"
        else:
            _set_unfinished(run, returncode, tail, where, sent=sent)


def _execute_at_url(run: PlannedRun, threads: int | None, watch: Callable[[], bool] | None = None) -> PlannedRun:
    """:func:`execute_run` for a run at a URL: train in the local scratch folder (downloaded from the URL first when
    it lacks the URL's latest checkpoint), upload after each checkpoint and at the end (:class:`RunMirror`)."""
    prepared = prepare_url_run(run)
    if prepared is None:
        return run
    local, mirror, action = prepared
    log = local.with_name(f"{run.run_id}.log")
    cmd = {
        "ran": _cli("run", run.recipe, *run.overrides, "-o", str(local), "--quiet"),
        "resumed": _cli("resume", str(local), "--quiet"),
        "uploaded": None,
    }[action]
    _record_attempt(run, event="start", action=action, scratch=str(local))
    start = time.perf_counter()
    returncode, sent, stopped, interrupted = 0, None, False, None
    if cmd is not None:
        with log.open("w") as fh:
            proc = start_training(cmd, fh, threads)
            with _live(proc) as sent_box:
                returncode, stopped, interrupted = wait_uploading(proc, watch, [(mirror, run.path)], fh)
            sent = sent_box[0]
    run.wall_time_s = time.perf_counter() - start
    finished_here = _ended_finished(returncode, local)
    settle_url_run(run, local, mirror, finished_here, returncode, log, action, stopped=stopped, sent=sent)
    if run.status == "finished":
        log.unlink(missing_ok=True)
    _record_attempt(run, event="end", action=action, status=run.status)
    if interrupted is not None:
        raise interrupted
    return run
