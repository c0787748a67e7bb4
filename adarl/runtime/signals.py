"""Graceful interruption: the first SIGINT/SIGTERM/SIGHUP asks the run to checkpoint and stop at the next safe point.

Safe points are between collector batches (after that batch's updates), where a checkpoint resumes exactly.
A second signal while the batch still runs stops at once (``KeyboardInterrupt``); the previous checkpoint is still
there. Once the stop itself has begun (:meth:`GracefulInterrupt.stopping`: the checkpoint is being written, the run
closed) further signals are noted and ignored: the stop is moments away, and a checkpoint cut short would lose the
work since the previous one. A signal after the last batch lets the run end as it would have (final evaluation,
checkpoint, summary.json, report.md), then stops it with the same exit status (:func:`stopped_after_the_end`): the
report is never cut short by a signal's default action.

SIGHUP (the terminal or the SSH session closed) is handled as SIGTERM, unless it was ignored when the run started
(``nohup``): then it stays ignored.
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
    "STOP_SIGNALS",
    "CHECKPOINTING",
    "FINISHING",
]

#: the signals that ask for a stop after a checkpoint: Ctrl-C, ``kill``/a scheduler, a closed terminal or SSH session
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))

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
    """Context manager: record the first SIGINT/SIGTERM/SIGHUP in ``requested``; raise KeyboardInterrupt on the
    second, unless the stop has begun (:meth:`stopping`): from then on further signals are noted and ignored.

    Outside the main thread (where Python cannot install handlers) it does nothing and ``requested`` stays None.
    A signal that was ignored when it was entered (SIGHUP under ``nohup``) stays ignored. :func:`stop_as_on_a_signal`
    asks the innermost one entered for the same stop without a signal (e.g. stdout's reader went away: SIGPIPE is
    never handled, so that a dropped socket elsewhere cannot stop anything).

    On leaving it the previous handlers come back, except in a process that ends after a stop
    (:attr:`process_ends_after_a_stop`, set by the ``adarl`` command): there the signals stay ignored once a stop was
    asked, so that a second signal cannot interrupt the process's exit (before: killed by it, exit -2, or a traceback
    from an exit handler).
    """

    _entered: list[GracefulInterrupt] = []  # main thread only, innermost last
    #: the ``adarl`` command sets it for its own process, which ends once a stop was asked (never in-process callers)
    process_ends_after_a_stop = False
    #: the signal that stopped a run at once (a second one), if any: whatever error follows is that stop's
    stopped_at_once: int | None = None

    def __init__(self, signals=STOP_SIGNALS, *, quiet: bool = False) -> None:
        self.signals = tuple(signals)
        self.quiet = quiet
        self.notice = CHECKPOINTING  # the loop sets FINISHING once training has ended
        self.requested: int | None = None
        self.stopping_since: str | None = None  # what the stop does, once it has begun (:meth:`stopping`)
        self._previous: dict[int, object] = {}

    def _handler(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self.stopping_since is not None:  # the stop has begun: never cut it short
            self._say(f"{name} received again: already stopping ({self.stopping_since}); it ends in a moment")
            return
        if self.requested is not None:
            GracefulInterrupt.stopped_at_once = signum
            self._restore(after_a_stop=True)
            raise KeyboardInterrupt
        self._request(signum, f"{name} received: {self.notice} (send it again to stop now)")

    def _request(self, signum: int, said: str) -> None:
        self.requested = signum
        self._say(said)

    def _say(self, said: str) -> None:
        """One notice on stderr, written straight to its file descriptor: a signal handler that printed through
        ``sys.stderr`` while the progress bar was writing to it raised "reentrant call" (a RuntimeError)."""
        if self.quiet:
            return
        text = f"\nadarl: {said}\n"
        try:
            fd = sys.stderr.fileno()
        except (AttributeError, OSError, ValueError):  # a replaced stderr (captured): no reentrancy to fear there
            print(text, end="", file=sys.stderr, flush=True)
            return
        try:
            os.write(fd, text.encode(errors="replace"))
        except OSError:  # stderr gone: nothing to tell
            pass

    def stopping(self, what: str) -> None:
        """The stop asked has begun (``what`` it does: "writing the checkpoint at N frames"); from now on a signal
        is noted and ignored instead of stopping at once. Says so, so that one waiting for it can tell."""
        self.stopping_since = what
        if self.requested is not None:
            self._say(f"stopping: {what}; a signal now is ignored until the run has stopped")

    def __enter__(self) -> GracefulInterrupt:
        if threading.current_thread() is threading.main_thread():
            for s in self.signals:
                previous = signal.getsignal(s)
                if s == getattr(signal, "SIGHUP", None) and previous is signal.SIG_IGN:
                    continue  # nohup: a hang-up was meant not to stop it
                self._previous[s] = previous
                signal.signal(s, self._handler)
            GracefulInterrupt._entered.append(self)
        return self

    def _restore(self, *, after_a_stop: bool = False) -> None:
        ignore = after_a_stop and GracefulInterrupt.process_ends_after_a_stop
        for s, h in self._previous.items():
            signal.signal(s, signal.SIG_IGN if ignore else h)
        self._previous.clear()

    def __exit__(self, *exc) -> None:
        self._restore(after_a_stop=self.requested is not None)
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
