"""What every launcher is: the :class:`Launcher` contract, the stop of an experiment on a signal
(:class:`ExperimentInterrupted`), and the driver-side helpers of the launchers whose runs train elsewhere."""

from __future__ import annotations

import contextlib
import signal
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator

from adarl.experiments.execute import (
    request_stop,
)
from adarl.experiments.packing import PlannedPack, members, settle
from adarl.runtime.signals import RunInterrupted


class ExperimentInterrupted(RunInterrupted):
    """An experiment stopped on SIGINT/SIGTERM (SIGPIPE: its output's reader went away): its running runs checkpointed
    and stopped, the others never started; the same ``adarl experiment`` command resumes them all. ``exit_code`` is
    128 + the signal number."""

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
    """Copy a worker's outcome (the run as ``execute_run`` returned it there, or a pack as ``execute_pack`` did, each
    of its runs set) onto the driver's run or pack."""
    for mine, theirs in zip(members(run), members(result), strict=True):
        mine.status, mine.message, mine.wall_time_s = theirs.status, theirs.message, theirs.wall_time_s
        mine.pack = theirs.pack
    if isinstance(run, PlannedPack):
        run.status, run.message, run.wall_time_s = result.status, result.message, result.wall_time_s
    return run


def _fail(unit, message: str):
    """A worker lost for good (its task raised, its job gone): each of the unit's runs that had not ended fails."""
    for r in members(unit):
        if r.status in ("pending", "running"):
            r.status, r.message = "failed", message
    if isinstance(unit, PlannedPack):
        settle(unit)
    else:
        unit.status, unit.message = "failed", message
    return unit


def _watch_remote(run, watch: Callable[[], bool], asked: list[bool]) -> None:
    """Driver side of a watched run on a worker: once ``watch()`` says stop, ask the run to stop (its stop file)."""
    if not asked[0] and watch():
        asked[0] = True
        request_stop(run.path)
