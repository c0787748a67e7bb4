"""Launchers: where an experiment's runs execute. ``local`` (a process pool on this machine, the default),
``ray`` (one Ray task per run, on an existing cluster or a Ray started on demand) and ``submitit`` (one SLURM job
per run, or submitit's local executor).

Every launcher runs the same thing: :func:`adarl.experiments.execute.execute_run`, which starts ``adarl run`` (or
``adarl resume`` when the run folder has a checkpoint) in a child process that dies with its launcher process. So a
worker that is lost mid-run is retried from the run's last checkpoint (Ray: ``max_retries``; submitit: resubmitted by
the driver, and requeued from the checkpoint on preemption/timeout), and a finished run is never started again. Runs
write into the experiment's output: a filesystem path that every worker sees (NFS, Lustre, ...), or an fsspec URL
(``s3://...``) that each run uploads to from a local scratch folder (:mod:`adarl.runtime.results`). The launchers do not
stage code or install packages on workers: each worker needs ``adarl`` installed (and the URL's fsspec backend, e.g.
``s3fs``, with its credentials), or the output folder mounted at the same path.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from adarl.errors import AdaRLValueError, MissingExtraError
from adarl.experiments.execute import (
    WATCH_POLL_S,
    StopAsked,
    clear_stop,
    execute_run,
    read_attempts,
    request_stop,
    signal_live_trainings,
)
from adarl.runtime.results import is_url
from adarl.runtime.signals import GracefulInterrupt, RunInterrupted

__all__ = [
    "Launcher",
    "LocalLauncher",
    "RayLauncher",
    "SubmititLauncher",
    "make_launcher",
    "LAUNCHERS",
    "ExperimentInterrupted",
]

LAUNCHERS = ("local", "ray", "submitit")


class ExperimentInterrupted(RunInterrupted):
    """An experiment stopped on SIGINT/SIGTERM: its running runs checkpointed and stopped, the others never started;
    the same ``adarl experiment`` command resumes them all. ``exit_code`` is 128 + the signal number."""

    def __init__(self, signum: int, stopped: list[str], not_started: int, *, at_once: bool = False) -> None:
        name = signal.Signals(signum).name
        which = f" ({', '.join(stopped[:5])}{' ...' if len(stopped) > 5 else ''})" if stopped else ""
        how = (
            "killed at once by a second signal (each keeps its last checkpoint)"
            if at_once
            else "stopped after a checkpoint"
        )
        super().__init__(
            f"experiment stopped on {name}: {len(stopped)} running runs {how}{which}, "
            f"{not_started} not started; run the same `adarl experiment` command to resume them",
            signum=signum,
            checkpoint=None,
        )
        self.stopped, self.not_started = stopped, not_started


class Launcher(ABC):
    """Runs a list of :class:`~adarl.experiments.spec.PlannedRun` and reports each one as it ends."""

    name = "launcher"

    @abstractmethod
    def launch(self, runs: list, on_done: Callable, *, tick: Callable[[set], None] = lambda running: None) -> None:
        """Execute ``runs``; call ``on_done(run)`` (status set) as each ends and ``tick(running_ids)`` now and then."""

    @property
    def threads(self) -> int | None:
        """Torch threads per run (``OMP_NUM_THREADS``); ``None`` leaves the default."""
        return None

    @contextlib.contextmanager
    def session(self) -> Iterator[Launcher]:
        """What :meth:`run_watched` needs held between runs (Ray started, submitit's executor), released after."""
        yield self

    def run_watched(self, run, watch: Callable[[], bool]):
        """Execute one run to its end (call it from any thread, inside :meth:`session`) and return it, status set.

        ``watch()`` is called here every :data:`~adarl.experiments.execute.WATCH_POLL_S` seconds while the run
        trains; once it returns True the run is asked to stop (:func:`~adarl.experiments.execute.request_stop`, a
        file beside its folder, seen by the worker: the training gets SIGTERM and checkpoints first) and its status is
        ``stopped`` (resumable). ``adarl tune`` prunes trials so."""
        raise NotImplementedError(f"the {self.name} launcher does not run watched runs (adarl tune)")


def _take_result(run, result):
    """Copy a worker's outcome (the run as ``execute_run`` returned it there) onto the driver's run."""
    run.status, run.message, run.wall_time_s = result.status, result.message, result.wall_time_s
    return run


def _ray_outcome(ray, ref, run):
    """The run of a finished Ray task, its status set; ``failed`` when the task raised (worker lost more than
    ``max_retries`` times, etc.)."""
    try:
        return _take_result(run, ray.get(ref))
    except Exception as err:  # noqa: BLE001 - any task failure is the run's failure, named
        run.status, run.message = "failed", f"ray: {type(err).__name__}: {str(err).splitlines()[0]}"
        return run


def _watch_remote(run, watch: Callable[[], bool], asked: list[bool]) -> None:
    """Driver side of a watched run on a worker: once ``watch()`` says stop, ask the run to stop (its stop file)."""
    if not asked[0] and watch():
        asked[0] = True
        request_stop(run.path)


class _RemoteStop:
    """The first-signal stop of the launchers whose runs train elsewhere (Ray tasks, submitit jobs), as the local
    launcher stops: on the first SIGINT/SIGTERM each unfinished run is asked to stop through its stop file
    (:func:`~adarl.experiments.execute.request_stop`: the worker's training gets SIGTERM and checkpoints after its
    batch; a worker that had not started its run returns without starting it). :meth:`raise_if_asked` then raises
    :class:`ExperimentInterrupted`. A second signal raises ``KeyboardInterrupt`` in the launcher's loop: it stops the
    runs at once (:meth:`killed_at_once`)."""

    def __init__(self, runs: list) -> None:
        self.runs, self.asked, self.at_once, self.since = runs, False, False, time.time()
        self.interrupt = GracefulInterrupt()
        self.interrupt.notice = "stopping the running runs after their next checkpoint, starting no other"
        for r in runs:
            clear_stop(r.path)  # a stop asked by an earlier driver that was killed before it withdrew it

    def __enter__(self) -> _RemoteStop:
        self.interrupt.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.interrupt.__exit__(*exc)
        if self.asked:
            for r in self.runs:
                clear_stop(r.path)

    def poll(self, unfinished: list) -> bool:
        """Ask ``unfinished`` runs to stop once the first signal came (the first time only); True once asked."""
        if self.interrupt.requested is not None and not self.asked:
            self.asked = True
            for r in unfinished:
                request_stop(r.path)
        return self.asked

    def outcome(self, run):
        """``run`` as its worker returned it: a run stopped through its stop file was interrupted by the signal."""
        if self.asked and run.status == "stopped":
            run.status = "interrupted"
            run.message = f"{signal.Signals(self.interrupt.requested).name} to its experiment: {run.message}"
        return run

    def started(self, run) -> bool:
        """Whether this launch started ``run`` (its attempts record a start since; a lost worker records no end)."""
        output = run.path.rsplit("/", 1)[0] if is_url(run.path) else Path(run.path).parent
        return any(
            e["event"] == "start" and e.get("time", 0) >= self.since - 1 for e in read_attempts(output, run.run_id)
        )

    def ended(self, run, why: str):
        """``run``, whose worker ended without its outcome (cancelled, killed at once): ``interrupted`` if it had
        started, else left ``pending`` (it never started)."""
        if self.started(run):
            run.status, run.message = "interrupted", f"{why}; resumes from its last checkpoint"
        return run

    def raise_if_asked(self) -> None:
        if self.interrupt.requested is not None:
            stopped = [r.run_id for r in self.runs if r.status == "interrupted"]
            never = sum(r.status == "pending" for r in self.runs)
            raise ExperimentInterrupted(self.interrupt.requested, stopped, never, at_once=self.at_once)


class LocalLauncher(Launcher):
    """``workers`` runs at a time on this machine, each in its own process (one torch thread each when > 1)."""

    name = "local"

    def __init__(self, workers: int = 1, poll_s: float = 5.0) -> None:
        if workers < 1:
            raise AdaRLValueError(f"workers must be >= 1, got {workers}")
        self.workers, self.poll_s = workers, poll_s

    @property
    def threads(self) -> int | None:
        return 1 if self.workers > 1 else None

    def launch(self, runs, on_done, *, tick=lambda running: None) -> None:
        """Run ``runs``, ``workers`` at a time. The first SIGINT or SIGTERM (called from the main thread) stops the
        experiment: no run starts after it, each running one is sent SIGTERM (it checkpoints after its batch and
        exits, ``interrupted``), and once they have ended :class:`ExperimentInterrupted` is raised; a second signal
        kills them at once (each keeps its last checkpoint)."""
        running: set[str] = set()
        at_once = False
        interrupt = GracefulInterrupt()
        interrupt.notice = "stopping the running runs after their next checkpoint, starting no other"

        def one(r):
            if interrupt.requested is not None:  # asked to stop before this run started: it never starts
                return r
            running.add(r.run_id)
            try:
                return execute_run(r, self.threads)
            finally:
                running.discard(r.run_id)

        with interrupt, ThreadPoolExecutor(max_workers=self.workers) as pool:
            futures = {pool.submit(one, r): r for r in runs}
            pending = set(futures)
            try:
                while pending:
                    if interrupt.requested is not None:
                        for f in pending:
                            f.cancel()
                        pending = {f for f in pending if not f.cancelled()}
                        signal_live_trainings(signal.SIGTERM)  # again each poll: a run that had just started
                    done = {f for f in pending if f.done()}
                    for f in done:
                        run = f.result()
                        if run.status != "pending":  # not one that was asked to stop before it started
                            on_done(run)
                    pending -= done
                    if pending:
                        tick(set(running))
                        time.sleep(min(self.poll_s, 0.2) if not done else 0)
            except BaseException as err:  # a second signal (KeyboardInterrupt), or a failure here: stop them at once
                signal_live_trainings(signal.SIGKILL)
                if not isinstance(err, KeyboardInterrupt) or interrupt.requested is None:
                    raise
                at_once = True
                for f in pending:
                    run = None if f.cancelled() else f.result()  # its process is gone: the thread returns at once
                    if run is not None and run.status != "pending":
                        on_done(run)
        if interrupt.requested is not None:
            stopped = [r.run_id for r in runs if r.status == "interrupted"]
            never = sum(r.status == "pending" for r in runs)
            raise ExperimentInterrupted(interrupt.requested, stopped, never, at_once=at_once)

    def run_watched(self, run, watch):
        return execute_run(run, self.threads, watch=watch)


def _ray_execute(run, threads, watch=None):
    return execute_run(run, threads, watch=watch)


class RayLauncher(Launcher):
    """One Ray task per run, declaring ``cpus_per_run``/``gpus_per_run``; a task whose worker dies is retried
    (``max_retries`` times) and resumes from the run's last checkpoint.

    ``address``: an existing cluster (``"auto"``, ``"ray://head:10001"``, ...); ``None`` starts a local Ray on demand
    (``num_cpus`` CPUs, no dashboard) and stops it afterwards. Needs ``pip install 'adarl[ray]'``.
    """

    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        *,
        cpus_per_run: float = 1,
        gpus_per_run: float = 0,
        max_retries: int = 3,
        num_cpus: int | None = None,
        poll_s: float = 5.0,
    ) -> None:
        if cpus_per_run <= 0 or gpus_per_run < 0 or max_retries < 0:
            raise AdaRLValueError(
                f"ray launcher: cpus_per_run must be > 0, gpus_per_run and max_retries >= 0 "
                f"(got {cpus_per_run}, {gpus_per_run}, {max_retries})"
            )
        self.address, self.cpus_per_run, self.gpus_per_run = address, cpus_per_run, gpus_per_run
        self.max_retries, self.num_cpus, self.poll_s = max_retries, num_cpus, poll_s

    @property
    def threads(self) -> int | None:
        return max(1, int(self.cpus_per_run))

    @contextlib.contextmanager
    def session(self):
        """Ray joined (``address``) or started on demand (stopped afterwards), and the run task declared."""
        try:
            import ray
        except ImportError:
            raise MissingExtraError("the ray launcher needs Ray: pip install 'adarl[ray]'") from None
        started = False
        if not ray.is_initialized():
            if self.address is None:
                ray.init(num_cpus=self.num_cpus, include_dashboard=False, log_to_driver=False, configure_logging=False)
            else:
                ray.init(address=self.address, log_to_driver=False, configure_logging=False)
            started = True
        try:
            self._task = ray.remote(_ray_execute).options(
                num_cpus=self.cpus_per_run,
                num_gpus=self.gpus_per_run,
                max_retries=self.max_retries,
                retry_exceptions=False,
            )
            yield self
        finally:
            self._task = None
            if started:
                ray.shutdown()

    def run_watched(self, run, watch):
        import ray

        ref, asked = self._task.remote(run, self.threads, StopAsked(run.path)), [False]
        try:
            while not ray.wait([ref], timeout=WATCH_POLL_S)[0]:
                _watch_remote(run, watch, asked)
        except BaseException:  # interrupted here: the run checkpoints and stops, if Ray lets it (a while)
            request_stop(run.path)
            with contextlib.suppress(BaseException):
                ray.wait([ref], timeout=60)
            raise
        _ray_outcome(ray, ref, run)
        if asked[0]:
            clear_stop(run.path)
        return run

    def launch(self, runs, on_done, *, tick=lambda running: None) -> None:
        """One task per run. The first SIGINT or SIGTERM stops the experiment as the local launcher does (through each
        run's stop file: the running ones checkpoint and stop, ``interrupted``; a task that starts afterwards returns
        without training); a second one cancels the tasks at once (each run keeps its last checkpoint)."""
        with self.session():
            import ray

            task = self._task
            stop = _RemoteStop(runs)
            with stop:
                refs = {task.remote(r, self.threads, StopAsked(r.path)): r for r in runs}
                pending = list(refs)
                try:
                    while pending:
                        stop.poll([refs[ref] for ref in pending])
                        done, pending = ray.wait(pending, num_returns=1, timeout=min(self.poll_s, 1.0))
                        for ref in done:
                            run = stop.outcome(_ray_outcome(ray, ref, refs[ref]))
                            if run.status != "pending":  # not one asked to stop before it started
                                on_done(run)
                        tick({refs[ref].run_id for ref in pending})
                except KeyboardInterrupt:
                    if stop.interrupt.requested is None:
                        raise
                    stop.at_once = True
                    for ref in pending:
                        with contextlib.suppress(Exception):
                            ray.cancel(ref, force=True)  # its worker dies, and its training with it
                        run = stop.ended(refs[ref], "killed at once by its launcher (a second signal)")
                        if run.status != "pending":
                            on_done(run)
            stop.raise_if_asked()


class SubmititLauncher(Launcher):
    """One submitit job per run: SLURM (``cluster=None`` picks it when ``sbatch`` exists) or ``cluster="local"``.

    Jobs are requeued from the run's checkpoint on preemption or timeout (submitit ``Checkpointable``); a job that
    fails otherwise (node lost) is resubmitted up to ``max_retries`` times. Needs ``pip install 'adarl[slurm]'``.
    """

    name = "submitit"

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        cluster: str | None = None,
        cpus_per_run: int = 1,
        gpus_per_run: int = 0,
        timeout_min: int = 24 * 60,
        slurm_partition: str | None = None,
        slurm_additional_parameters: dict | None = None,
        max_retries: int = 3,
        poll_s: float = 5.0,
    ) -> None:
        self.folder, self.cluster = Path(folder), cluster
        self.cpus_per_run, self.gpus_per_run, self.timeout_min = int(cpus_per_run), int(gpus_per_run), timeout_min
        self.slurm_partition, self.slurm_additional_parameters = slurm_partition, slurm_additional_parameters or {}
        self.max_retries, self.poll_s = max_retries, poll_s

    @property
    def threads(self) -> int | None:
        return max(1, self.cpus_per_run)

    def _executor(self):
        try:
            import submitit
        except ImportError:
            raise MissingExtraError("the submitit launcher needs submitit: pip install 'adarl[slurm]'") from None
        ex = submitit.AutoExecutor(folder=self.folder, cluster=self.cluster)
        params = dict(timeout_min=self.timeout_min, cpus_per_task=self.cpus_per_run, nodes=1, tasks_per_node=1)
        if self.gpus_per_run:
            params["gpus_per_node"] = self.gpus_per_run
        if ex.cluster == "slurm":
            if self.slurm_partition:
                params["slurm_partition"] = self.slurm_partition
            if self.slurm_additional_parameters:
                params["slurm_additional_parameters"] = self.slurm_additional_parameters
        ex.update_parameters(**params)
        return ex

    @contextlib.contextmanager
    def session(self):
        """submitit's executor, made once for the runs sent one by one."""
        self._ex = self._executor()
        try:
            yield self
        finally:
            self._ex = None

    def _settled(self, job, run, tries: int) -> bool:
        """Set ``run``'s status from its finished ``job``; False when the job was lost (node failure, cancelled)
        and is to be submitted again (``tries`` below ``max_retries``: the run resumes from its checkpoint)."""
        try:
            _take_result(run, job.result())
        except Exception as err:  # noqa: BLE001 - a lost job is retried, then the run's failure, named
            if tries < self.max_retries:
                return False
            run.status, run.message = "failed", f"submitit job {job.job_id}: {str(err).splitlines()[0]}"
        return True

    def run_watched(self, run, watch):
        job_fn, asked = _CheckpointableRun(), [False]
        job, tries = self._ex.submit(job_fn, run, self.threads, StopAsked(run.path)), 0
        while True:
            if job.done():
                if not self._settled(job, run, tries):
                    job, tries = self._ex.submit(job_fn, run, self.threads, StopAsked(run.path)), tries + 1
                    continue
                break
            try:
                _watch_remote(run, watch, asked)
                time.sleep(WATCH_POLL_S)
            except BaseException:  # interrupted here: the job's run checkpoints and stops (asked by its folder)
                request_stop(run.path)
                raise
        if asked[0]:
            clear_stop(run.path)
        return run

    def launch(self, runs, on_done, *, tick=lambda running: None) -> None:
        """One job per run. The first SIGINT or SIGTERM stops the experiment as the local launcher does (through each
        run's stop file: the running ones checkpoint and stop, ``interrupted``; jobs still queued are cancelled and
        never start; no job is resubmitted); a second one cancels every job at once (each keeps its last checkpoint)."""
        ex = self._executor()
        job_fn = _CheckpointableRun()

        def submit(run):
            return ex.submit(job_fn, run, self.threads, StopAsked(run.path))

        stop = _RemoteStop(runs)
        with stop:
            jobs = {r.run_id: (submit(r), r, 0) for r in runs}
            try:
                while jobs:
                    if not stop.asked and stop.poll([run for _, run, _ in jobs.values()]):
                        for job, _, _ in jobs.values():
                            if _job_state(job) == "PENDING":  # still queued: it never starts
                                with contextlib.suppress(Exception):
                                    job.cancel(check=False)
                    for run_id, (job, run, tries) in list(jobs.items()):
                        if not job.done():
                            continue
                        if stop.asked:  # nothing is resubmitted after the stop
                            del jobs[run_id]
                            try:
                                run = stop.outcome(_take_result(run, job.result()))
                            except Exception as err:  # noqa: BLE001 - cancelled in the queue, or lost
                                run = stop.ended(
                                    run, f"its job {job.job_id} ended after the stop ({type(err).__name__})"
                                )
                            if run.status != "pending":
                                on_done(run)
                            continue
                        if not self._settled(job, run, tries):
                            jobs[run_id] = (submit(run), run, tries + 1)
                            continue
                        del jobs[run_id]
                        on_done(run)
                    if jobs:
                        tick(set(jobs))
                        time.sleep(min(self.poll_s, 1.0))
            except KeyboardInterrupt:
                if stop.interrupt.requested is None:
                    raise
                stop.at_once = True
                for job, run, _ in jobs.values():
                    with contextlib.suppress(Exception):
                        job.cancel(check=False)
                    if stop.ended(run, "killed at once by its launcher (a second signal)").status != "pending":
                        on_done(run)
        stop.raise_if_asked()


def _job_state(job) -> str:
    """A submitit job's scheduler state (``PENDING``: queued, not started); ``UNKNOWN`` when it cannot be read."""
    try:
        return str(job.state)
    except Exception:  # noqa: BLE001 - the scheduler does not answer: treat it as started (it is asked to stop)
        return "UNKNOWN"


try:  # submitit's requeue-on-preemption protocol, when submitit is installed
    from submitit.helpers import Checkpointable as _Checkpointable
except ImportError:  # pragma: no cover - the launcher raises a clear error before this is used
    _Checkpointable = object


class _CheckpointableRun(_Checkpointable):
    """The job submitit runs; on preemption/timeout it is resubmitted as is (the run resumes from its checkpoint)."""

    def __call__(self, run, threads, watch=None):
        return execute_run(run, threads, watch=watch)


def make_launcher(
    name: str,
    *,
    workers: int = 1,
    output: str | os.PathLike = ".",
    address: str | None = None,
    cpus_per_run: float | None = None,
    gpus_per_run: float | None = None,
    max_retries: int = 3,
    resources=None,
    cluster: str | None = None,
    submitit_folder: str | os.PathLike | None = None,
) -> Launcher:
    """A launcher by name (``local``, ``ray``, ``submitit``), sized from the spec's ``resources`` unless given.

    ``submitit_folder``: where submitit keeps its job files (default ``<output>/submitit``; required when the output
    is a URL, since SLURM jobs read them from a shared filesystem)."""
    if name not in LAUNCHERS:
        raise AdaRLValueError(f"unknown launcher {name!r}; choose one of {', '.join(LAUNCHERS)}")
    cpus = cpus_per_run if cpus_per_run is not None else (resources.cpus_per_run if resources else 1)
    gpus = gpus_per_run if gpus_per_run is not None else (resources.gpus_per_run if resources else 0)
    if name == "local":
        return LocalLauncher(workers)
    package, extra = {"ray": ("ray", "ray"), "submitit": ("submitit", "slurm")}[name]
    if importlib.util.find_spec(package) is None:  # before the experiment writes anything
        raise MissingExtraError(f"the {name} launcher needs {package}: pip install 'adarl[{extra}]'")
    if name == "ray":
        return RayLauncher(address, cpus_per_run=cpus, gpus_per_run=gpus, max_retries=max_retries)
    if submitit_folder is None and is_url(output):
        raise AdaRLValueError(
            f"the submitit launcher keeps its job files in a folder every job can read; with an "
            f"fsspec URL as output ({output}) give one: --submitit-folder /shared/path"
        )
    folder = Path(submitit_folder) if submitit_folder is not None else Path(output) / "submitit"
    return SubmititLauncher(
        folder,
        cluster=cluster,
        cpus_per_run=int(cpus),
        gpus_per_run=int(gpus),
        timeout_min=resources.timeout_min if resources else 24 * 60,
        slurm_partition=resources.slurm_partition if resources else None,
        slurm_additional_parameters=resources.slurm_additional_parameters if resources else None,
        max_retries=max_retries,
    )
