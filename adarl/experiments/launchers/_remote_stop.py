"""The first-signal stop of the launchers whose runs train elsewhere: through each run's stop file."""

from __future__ import annotations

import signal
import time
from pathlib import Path

from adarl.experiments.execute import (
    clear_stop,
    read_attempts,
    request_stop,
    run_is_finished,
)
from adarl.experiments.launchers._base import ExperimentInterrupted
from adarl.experiments.packing import PlannedPack, members, settle
from adarl.runtime.run_folder.results import is_url
from adarl.runtime.signals import GracefulInterrupt


class _RemoteStop:
    """The first-signal stop of the launchers whose runs train elsewhere (Ray tasks, submitit jobs), as the local
    launcher stops: on the first SIGINT/SIGTERM each unfinished run is asked to stop through its stop file
    (:func:`~adarl.experiments.execute.request_stop`: the worker's training gets SIGTERM and checkpoints after its
    batch; a worker that had not started its run returns without starting it). :meth:`raise_if_asked` then raises
    :class:`ExperimentInterrupted`. A second signal raises ``KeyboardInterrupt`` in the launcher's loop: it stops the
    runs at once (:meth:`ended` then says what became of each)."""

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

    def outcome(self, unit):
        """``unit`` (a run, or a pack of runs) as its worker returned it: a run stopped through its stop file was
        interrupted by the signal."""
        for run in members(unit):
            if self.asked and run.status == "stopped":
                run.status = "interrupted"
                run.message = f"{signal.Signals(self.interrupt.requested).name} to its experiment: {run.message}"
        return _settled(unit)

    def started(self, run) -> bool:
        """Whether this launch started ``run`` (its attempts record a start since; a lost worker records no end)."""
        output = run.path.rsplit("/", 1)[0] if is_url(run.path) else Path(run.path).parent
        return any(
            e["event"] == "start" and e.get("time", 0) >= self.since - 1 for e in read_attempts(output, run.run_id)
        )

    def ended(self, unit, why: str):
        """``unit`` (a run, or a pack of runs), whose worker ended without its outcome (cancelled, killed at once,
        interrupted itself): each run ``finished`` if its budget is spent, ``interrupted`` if it had started, else
        left ``pending``."""
        for run in members(unit):
            if run_is_finished(run.path):
                run.status, run.message = "finished", f"finished ({why} after it)"
            elif self.started(run):
                run.status, run.message = "interrupted", f"{why}; resumes from its last checkpoint"
        return _settled(unit)

    def raise_if_asked(self) -> None:
        if self.interrupt.requested is not None:
            each = [r for unit in self.runs for r in members(unit)]
            stopped = [r.run_id for r in each if r.status == "interrupted"]
            never = sum(r.status == "pending" for r in each)
            raise ExperimentInterrupted(self.interrupt.requested, stopped, never, at_once=self.at_once)


def _settled(unit):
    """A pack's own status from its runs' (a run is its own)."""
    if isinstance(unit, PlannedPack):
        settle(unit)
    return unit
