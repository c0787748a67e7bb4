"""The ``submitit`` launcher: one SLURM job (or submitit local job) per run."""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path

from adarl.errors import AdaRLError, MissingExtraError
from adarl.experiments.execute import (
    WATCH_POLL_S,
    StopAsked,
    clear_stop,
    request_stop,
)
from adarl.experiments.launchers._base import Launcher, _fail, _take_result, _watch_remote
from adarl.experiments.launchers._remote_stop import _RemoteStop
from adarl.experiments.packing import execute_unit


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
        cluster = _slurm_or_refused(self.cluster)
        try:
            ex = submitit.AutoExecutor(folder=self.folder, cluster=cluster)
        except (RuntimeError, ValueError) as err:  # submitit found no executor it can use here
            raise AdaRLError(f"the submitit launcher cannot start: {str(err).splitlines()[0]}") from None
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
            _fail(run, f"submitit job {job.job_id}: {str(err).splitlines()[0]}")
        return True

    def run_watched(self, run, watch):
        job_fn, asked = _CheckpointableRun(), [False]
        job, tries = _submit(self._ex, job_fn, run, self.threads), 0
        while True:
            if job.done():
                if not self._settled(job, run, tries):
                    job, tries = _submit(self._ex, job_fn, run, self.threads), tries + 1
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
            return _submit(ex, job_fn, run, self.threads)

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


def _slurm_or_refused(cluster: str | None) -> str | None:
    """The cluster to give submitit: ``slurm`` needs both ``sbatch`` (to submit) and ``srun`` (to start the job);
    without them it is refused in one line naming what is missing (before: submitit's RuntimeError, or sbatch's
    FileNotFoundError at the first submission, as tracebacks). ``None`` with neither: submitit's local executor."""
    if cluster not in (None, "slurm"):
        return cluster
    missing = [exe for exe in ("sbatch", "srun") if shutil.which(exe) is None]
    if not missing:
        return "slurm"
    if cluster is None and len(missing) == 2:
        return None  # no SLURM here: submitit picks its local executor
    raise AdaRLError(
        f"the submitit launcher's slurm cluster needs {' and '.join(missing)}, which "
        f"{'is' if len(missing) == 1 else 'are'} not on this machine's PATH: run it on a SLURM login node, or "
        f"use --submitit-cluster local"
    )


def _submit(ex, job_fn, run, threads):
    """Submit ``run``'s job; a submission the scheduler refuses (sbatch's error) is one line naming it."""
    try:
        return ex.submit(job_fn, run, threads, StopAsked(run.path))
    except Exception as err:  # noqa: BLE001 - sbatch's errors come back as submitit's FailedJobError, OSError, ...
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise AdaRLError(f"the submitit launcher could not submit run {run.run_id}: {first}") from None


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
        return execute_unit(run, threads, watch=watch)  # a run, or a pack of runs (adarl.experiments.packing)
