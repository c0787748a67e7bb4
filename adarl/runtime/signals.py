"""Graceful interruption: the first SIGINT/SIGTERM asks the run to checkpoint and stop at the next safe point.

Safe points are between collector batches (after that batch's updates), where a checkpoint resumes exactly.
A second signal stops at once (``KeyboardInterrupt``); the previous checkpoint is still there. A signal after the
last batch lets the run end as it would have (final evaluation, checkpoint, summary.json, report.md), then stops it
with the same exit status (:func:`stopped_after_the_end`): the report is never cut short by a signal's default
action.
"""

from __future__ import annotations

import signal
import sys
import threading

from adarl.errors import AdaRLError

__all__ = ["GracefulInterrupt", "RunInterrupted", "stopped_after_the_end", "CHECKPOINTING", "FINISHING"]

#: what the first signal's notice says is done before stopping, in training and once training has ended
CHECKPOINTING = "saving a checkpoint after this batch"
FINISHING = "the run has finished training: writing its summary and report first"


class RunInterrupted(AdaRLError):
    """The run stopped on a signal after saving a checkpoint; ``exit_code`` is 128 + the signal number."""

    def __init__(self, message: str, *, signum: int, checkpoint) -> None:
        super().__init__(message)
        self.signum, self.checkpoint = signum, checkpoint
        self.exit_code = 128 + int(signum)


class GracefulInterrupt:
    """Context manager: record the first SIGINT/SIGTERM in ``requested``; raise KeyboardInterrupt on the second.

    Outside the main thread (where Python cannot install handlers) it does nothing and ``requested`` stays None.
    """

    def __init__(self, signals=(signal.SIGINT, signal.SIGTERM), *, quiet: bool = False) -> None:
        self.signals = tuple(signals)
        self.quiet = quiet
        self.notice = CHECKPOINTING  # the loop sets FINISHING once training has ended
        self.requested: int | None = None
        self._previous: dict[int, object] = {}

    def _handler(self, signum, frame) -> None:
        if self.requested is not None:
            self._restore()
            raise KeyboardInterrupt
        self.requested = signum
        if not self.quiet:
            print(
                f"\nadarl: {signal.Signals(signum).name} received: {self.notice} (send it again to stop now)",
                file=sys.stderr,
                flush=True,
            )

    def __enter__(self) -> GracefulInterrupt:
        if threading.current_thread() is threading.main_thread():
            for s in self.signals:
                self._previous[s] = signal.getsignal(s)
                signal.signal(s, self._handler)
        return self

    def _restore(self) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()

    def __exit__(self, *exc) -> None:
        self._restore()


def stopped_after_the_end(signum: int, frames: int, checkpoint, run_dir) -> RunInterrupted:
    """The stop of a signal received after the last batch: the run had ended, and its summary and report are
    written; it exits with the signal's status, as a stop in training does."""
    name = signal.Signals(signum).name
    return RunInterrupted(
        f"stopped on {name} at the end of the run ({frames} frames): it had finished training; its last checkpoint "
        f"{checkpoint.name}, summary.json and report.md are written in {str(run_dir)!r}",
        signum=signum,
        checkpoint=checkpoint,
    )
