"""A watched run waits, after each evaluation, for its watcher's verdict before it trains on.

``adarl tune`` watches each trial's runs: its pruner reads their ``eval.csv`` and stops a trial that falls behind.
Without a handshake, whether a run is pruned at an evaluation depended on the race between the trainer and the
watcher's poll (a short run could train past the evaluation that should prune it, and end complete). As in Optuna's
in-process ``trial.report`` / ``should_prune`` and Ray Tune's function API, the run instead holds after each
evaluation until its watcher has read it: the watcher says so in a file beside the run folder (``.<name>.watch``,
beside it for the reason the stop file is: a run's first start clears its folder), or stops the run (SIGTERM: it
checkpoints). A run whose file is absent is not watched and never waits; a watcher that stops refreshing its file
(its process gone) lets the run train on after :data:`STALE_S` seconds, said once.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from adarl.runtime.run_folder._file_safety import atomic_write_text

#: a watcher whose file a held run sees unchanged for this long is taken as gone: the run trains on
STALE_S = 60.0
#: a live watcher rewrites its file at least this often, new verdict or not
REFRESH_S = 5.0
_POLL_S = 0.02  # how often a held run reads its watcher's file


def watch_file(path: str | os.PathLike) -> Path:
    """The watcher's file of the run in the folder ``path``: ``.<name>.watch`` beside the folder."""
    p = Path(path)
    return p.parent / f".{p.name}.watch"


class Watcher:
    """The watcher's side: :meth:`start` before the run is launched, :meth:`seen` after each poll that read the run's
    evaluations up to ``frames`` and did not stop it, :meth:`close` once the run has ended."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.file = watch_file(path)
        self._said: tuple[int, float] | None = None

    def start(self) -> None:
        self._write(-1)

    def seen(self, frames: int) -> None:
        """The evaluations up to ``frames`` were read and the run goes on (rewritten when new, or to stay fresh)."""
        said = self._said
        if said is None or frames != said[0] or time.monotonic() - said[1] >= REFRESH_S:
            self._write(frames)

    def close(self) -> None:
        self.file.unlink(missing_ok=True)
        self._said = None

    def _write(self, frames: int) -> None:
        self.file.parent.mkdir(parents=True, exist_ok=True)  # a trial's folder, before its seeds' runs made it
        atomic_write_text(self.file, json.dumps({"seen": int(frames), "pid": os.getpid()}) + "\n")
        self._said = (int(frames), time.monotonic())


@contextlib.contextmanager
def watching(watchers: Sequence[Watcher]) -> Iterator[None]:
    """Each watcher's file there while the block runs its runs (started before them), gone after, however it ends."""
    try:
        for watcher in watchers:
            watcher.start()
        yield
    finally:
        for watcher in watchers:
            watcher.close()


def await_verdict(path: str | os.PathLike, frames: int, stopping: Callable[[], bool], *, quiet: bool = False) -> str:
    """Hold the run in ``path`` after its evaluation at ``frames`` until its watcher has read it, ``stopping()`` is
    true (the watcher's SIGTERM arrived) or the watcher is gone: its file unchanged for :data:`STALE_S` seconds of
    this process's own clock (no comparison with the watcher's clock, which may be another machine's). Returns which:
    ``"unwatched"``, ``"seen"``, ``"stopping"`` or ``"stale"``."""
    f = watch_file(path)
    last, changed = None, time.monotonic()
    while True:
        try:
            stamp = f.stat().st_mtime_ns
            seen = int(json.loads(f.read_text())["seen"])
        except FileNotFoundError:
            return "unwatched"
        except (OSError, ValueError, KeyError, TypeError):  # replaced between the stat and the read: read it again
            stamp, seen = last, -1
        if seen >= frames:
            return "seen"
        if stopping():
            return "stopping"
        if stamp != last:
            last, changed = stamp, time.monotonic()
        elif time.monotonic() - changed > STALE_S:
            if not quiet:
                print(
                    f"adarl: the watcher of this run ({f}) has not answered for {STALE_S:g} s: training on without "
                    f"its verdict on the evaluation at {frames} frames, nor waiting for it again",
                    file=sys.stderr,
                    flush=True,
                )
            return "stale"
        time.sleep(_POLL_S)
