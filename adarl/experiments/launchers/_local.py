"""The ``local`` launcher: a pool of training processes on this machine."""

from __future__ import annotations

import signal
import time
from concurrent.futures import ThreadPoolExecutor

from adarl.errors import AdaRLValueError
from adarl.experiments.execute import (
    execute_run,
    signal_live_trainings,
)
from adarl.experiments.launchers._base import ExperimentInterrupted, Launcher
from adarl.experiments.packing import execute_unit, members
from adarl.runtime.signals import GracefulInterrupt


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
        at_once, broken = False, [False]  # broken: this loop failed (or a second signal): no queued run may start
        interrupt = GracefulInterrupt()
        interrupt.notice = "stopping the running runs after their next checkpoint, starting no other"

        def one(r):
            if interrupt.requested is not None or broken[0]:  # stopping before this run started: it never starts
                return r
            running.add(r.run_id)
            try:
                return execute_unit(r, self.threads)  # a run, or a pack of runs (adarl.experiments.packing)
            except BaseException:  # (its output folder went, ...): this thread must not take the next queued run
                broken[0] = True
                raise
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
                broken[0] = True
                signal_live_trainings(signal.SIGKILL)
                if not isinstance(err, KeyboardInterrupt) or interrupt.requested is None:
                    for f in pending:  # none of the queued runs starts (before, they all trained first)
                        f.cancel()
                    while not all(f.done() for f in pending):  # and one that was starting as this failed is killed
                        signal_live_trainings(signal.SIGKILL)
                        time.sleep(0.05)
                    raise
                at_once = True
                for f in pending:
                    run = None if f.cancelled() else f.result()  # its process is gone: the thread returns at once
                    if run is not None and run.status != "pending":
                        on_done(run)
        if interrupt.requested is not None:
            each = [m for r in runs for m in members(r)]
            stopped = [r.run_id for r in each if r.status == "interrupted"]
            never = sum(r.status == "pending" for r in each)
            raise ExperimentInterrupted(interrupt.requested, stopped, never, at_once=at_once)

    def run_watched(self, run, watch):
        return execute_run(run, self.threads, watch=watch)
