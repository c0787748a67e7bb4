"""The kernel lock on a run folder's ``.adarl.lock``: one process trains in a folder at a time; and
:func:`exclusive_lock`, the same lock held over a block: one ``adarl experiment`` (or ``adarl tune``) per output folder.

Behind :mod:`adarl.runtime.run_folder.run_dir`, which re-exports :func:`exclusive_lock`. ``flock`` is dropped by the
kernel when
its process dies (kill -9 included), so a crashed run never leaves a stale lock; the file says who holds it, for the
message another process gets. On systems without ``fcntl`` folders are still created exclusively, but not locked while
in use.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path

try:  # POSIX: a lock the kernel drops when its process dies (kill -9 included)
    import fcntl
except ImportError:  # pragma: no cover - Windows: folders are still created exclusively, but not locked while in use
    fcntl = None

__all__ = ["HELD_LOCKS", "KERNEL_LOCKS", "hold_lock", "holder", "release_lock", "exclusive_lock"]

KERNEL_LOCKS = fcntl is not None  # whether a lock excludes other processes (False: Windows)
HELD_LOCKS: dict[str, int] = {}  # lock files this process holds (path -> fd): a lock excludes other processes only


def hold_lock(lock: Path, fd: int) -> bool:
    """Take the kernel lock on ``fd`` (False, fd closed, when another process holds it) and note who holds it."""
    if fcntl is not None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            return False
    with contextlib.suppress(OSError):  # who holds it, for the message another process gets
        os.ftruncate(fd, 0)
        os.pwrite(
            fd,
            json.dumps(
                {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
            ).encode(),
            0,
        )
    HELD_LOCKS[str(lock.absolute())] = fd
    return True


def release_lock(lock: Path) -> None:
    """Drop this process's lock on ``lock`` (nothing when it holds none)."""
    fd = HELD_LOCKS.pop(str(lock.absolute()), None)
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)  # closing the only descriptor drops the kernel lock


def holder(lock: Path) -> str:
    """Who holds ``lock``, as its file says (``pid 12 on host, since ...``), for a refusal's message."""
    try:
        info = json.loads(lock.read_text())
        return f"pid {info['pid']} on {info['host']}, since {info['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown"


@contextlib.contextmanager
def exclusive_lock(lock: Path, refused: Callable[[str], Exception]) -> Iterator[None]:
    """Hold the kernel lock on the file ``lock`` (created if missing) while the block runs; when another process
    holds it, raise ``refused(who)`` (``who``: ``pid N on host, since ...``) before the block starts. A killed holder
    holds it no more (the kernel drops it), so nothing stale is left to clean."""
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    if not hold_lock(lock, fd):
        raise refused(holder(lock))
    try:
        yield
    finally:
        release_lock(lock)
