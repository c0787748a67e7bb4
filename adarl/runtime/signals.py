"""Graceful interruption: the first SIGINT/SIGTERM asks the run to checkpoint and stop at the next safe point.

Safe points are between collector batches (after that batch's updates), where a checkpoint resumes exactly.
A second signal stops at once (``KeyboardInterrupt``); the previous checkpoint is still there. A signal after the
last batch lets the run end as it would have (final evaluation, checkpoint, summary.json, report.md), then stops it
with the same exit status (:func:`stopped_after_the_end`): the report is never cut short by a signal's default
action.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading

from adarl.errors import AdaRLError

__all__ = [
    "GracefulInterrupt",
    "RunInterrupted",
    "stopped_after_the_end",
    "stop_as_on_a_signal",
    "stdout_reader_gone",
    "silence_stdout",
    "CHECKPOINTING",
    "FINISHING",
]

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
    :func:`stop_as_on_a_signal` asks the innermost one entered for the same stop without a signal (e.g. stdout's
    reader went away: SIGPIPE is never handled, so that a dropped socket elsewhere cannot stop anything).
    """

    _entered: list[GracefulInterrupt] = []  # main thread only, innermost last

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
        self._request(signum, f"{signal.Signals(signum).name} received: {self.notice} (send it again to stop now)")

    def _request(self, signum: int, said: str) -> None:
        self.requested = signum
        if not self.quiet:
            print(f"\nadarl: {said}", file=sys.stderr, flush=True)

    def __enter__(self) -> GracefulInterrupt:
        if threading.current_thread() is threading.main_thread():
            for s in self.signals:
                self._previous[s] = signal.getsignal(s)
                signal.signal(s, self._handler)
            GracefulInterrupt._entered.append(self)
        return self

    def _restore(self) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h)
        self._previous.clear()

    def __exit__(self, *exc) -> None:
        self._restore()
        if self in GracefulInterrupt._entered:
            GracefulInterrupt._entered.remove(self)


def stop_as_on_a_signal(signum: int, why: str) -> bool:
    """Ask the innermost :class:`GracefulInterrupt` entered in the main thread for the stop its first ``signum``
    would ask (one that has a stop requested already keeps it); False when none is entered."""
    if threading.current_thread() is not threading.main_thread() or not GracefulInterrupt._entered:
        return False
    interrupt = GracefulInterrupt._entered[-1]
    if interrupt.requested is None:
        interrupt._request(signum, f"{why}: {interrupt.notice}")
    return True


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


def stdout_reader_gone() -> bool:
    """Whether stdout is a pipe or socket whose reader went away (``adarl recipes | head`` after ``head`` exited):
    poll reports an error or hang-up on its write end. A BrokenPipeError from anything else is a real failure."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no real file behind stdout (captured, closed)
        return False


def silence_stdout() -> None:
    """Send what is still to be written to stdout to /dev/null: after its reader went away, a later print (or the
    interpreter's last flush) must not fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
