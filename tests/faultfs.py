"""File-system faults for the tests: a small or read-only tmpfs where this machine lets us mount one, otherwise the
same faults injected in-process.

``small_fs(size)`` / ``readonly_fs()`` mount a real tmpfs (root, or CAP_SYS_ADMIN) and yield its path; they skip
the test where ``mount`` is not allowed (or with ``ADARL_TESTS_NO_MOUNT=1``: the CI path, on a machine that can).
:class:`FaultFS` makes every path under a folder behave as on a full (``ENOSPC`` once a byte budget is spent) or
read-only (``EROFS``) file system, for code in this process: it patches ``open``/``io.open`` (writes counted
through a proxy file), ``os.open``/``os.write``/``os.pwrite`` and the calls that create, rename or delete.
``python tests/faultfs.py ROOT MODE BUDGET -- ARGS`` runs ``adarl ARGS`` under it, so the CLI tests cover the same
behaviour where nothing can be mounted (CI without root).
"""

from __future__ import annotations

import builtins
import contextlib
import errno
import io
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

__all__ = ["FaultFS", "can_mount", "small_fs", "readonly_fs", "remount"]


def _mount(target: Path, options: str) -> bool:
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(target)], capture_output=True)
    return proc.returncode == 0


def _umount(target: Path) -> None:
    subprocess.run(["umount", "-l", str(target)], capture_output=True)


_CAN_MOUNT: bool | None = None


def can_mount() -> bool:
    """Whether this process may mount a tmpfs (tried once: root in a container may still lack CAP_SYS_ADMIN)."""
    global _CAN_MOUNT
    if _CAN_MOUNT is None:
        if (
            os.environ.get("ADARL_TESTS_NO_MOUNT")
            or shutil.which("mount") is None
            or not sys.platform.startswith("linux")
        ):
            _CAN_MOUNT = False
        else:
            probe = Path(tempfile.mkdtemp(prefix="adarl-mount-probe-"))
            _CAN_MOUNT = _mount(probe, "size=64k")
            if _CAN_MOUNT:
                _umount(probe)
            probe.rmdir()
    return _CAN_MOUNT


@contextlib.contextmanager
def small_fs(size: str, *, tmp: Path):
    """A real tmpfs of ``size`` (e.g. ``"3m"``) at ``tmp/fs``; skips the test where mounting is not allowed."""
    import pytest

    if not can_mount():
        pytest.skip("mounting a tmpfs is not allowed here (the FaultFS variant of this test covers it)")
    target = tmp / "fs"
    target.mkdir()
    assert _mount(target, f"size={size}")
    try:
        yield target
    finally:
        _umount(target)


def remount(target: Path, options: str) -> None:
    """Change a mounted tmpfs's options, e.g. ``"ro"`` or ``"size=20m"``."""
    proc = subprocess.run(["mount", "-o", f"remount,{options}", str(target)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@contextlib.contextmanager
def readonly_fs(*, tmp: Path, populate=None):
    """A real read-only tmpfs at ``tmp/fs``, filled first by ``populate(path)`` when given; skips where mounting is
    not allowed."""
    with small_fs("32m", tmp=tmp) as target:
        if populate is not None:
            populate(target)
        remount(target, "ro")
        yield target


class _BudgetedFile:
    """A file whose writes draw on :class:`FaultFS`'s byte budget; ENOSPC once it is spent (after writing what fits)."""

    def __init__(self, fh, fs: FaultFS, name: str) -> None:
        self._fh, self._fs, self._name = fh, fs, name

    def write(self, data):
        n = len(data.encode()) if isinstance(data, str) else memoryview(data).nbytes
        room = self._fs._take(n)
        if room < n:
            if room and not isinstance(data, str):
                self._fh.write(bytes(memoryview(data).cast("B")[:room]))
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self._name)
        return self._fh.write(data)

    def __getattr__(self, name):
        return getattr(self._fh, name)

    def __iter__(self):
        return iter(self._fh)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._fh.close()


class FaultFS:
    """Paths under ``root`` behave as on a full (``mode="full"``: writes fail with ENOSPC once ``budget`` bytes are
    written) or read-only (``mode="readonly"``: anything that writes fails with EROFS) file system, in this process."""

    _WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND

    def __init__(self, root, mode: str, budget: int = 0) -> None:
        assert mode in ("full", "readonly"), mode
        self.root = os.path.abspath(root)
        self.mode, self.budget = mode, int(budget)
        self._saved: dict = {}
        self._fds: set[int] = set()

    # ------------------------------------------------------------------ bookkeeping
    def _under(self, path, dir_fd=None) -> bool:
        if dir_fd is not None or isinstance(path, int):
            return False
        try:
            p = os.path.abspath(os.fsdecode(path))
        except TypeError:
            return False
        return p == self.root or p.startswith(self.root + os.sep)

    def _take(self, n: int) -> int:
        room = max(0, min(n, self.budget))
        self.budget -= room
        return room

    def _erofs(self, path):
        return OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))

    # ------------------------------------------------------------------ patched calls
    def _open(self, file, mode="r", *args, **kwargs):
        real = self._saved["open"]
        writes = any(c in mode for c in "wax+")
        if not writes or not self._under(file):
            return real(file, mode, *args, **kwargs)
        if self.mode == "readonly":
            raise self._erofs(file)
        return _BudgetedFile(real(file, mode, *args, **kwargs), self, os.fsdecode(file))

    def _os_open(self, path, flags, mode=0o777, *, dir_fd=None):
        fd = (
            self._saved["os.open"](path, flags, mode, dir_fd=dir_fd)
            if not (self.mode == "readonly" and flags & self._WRITE_FLAGS and self._under(path, dir_fd))
            else None
        )
        if fd is None:
            raise self._erofs(path)
        if self.mode == "full" and flags & self._WRITE_FLAGS and self._under(path, dir_fd):
            self._fds.add(fd)
        return fd

    def _os_write(self, fd, data):
        if fd in self._fds and self._take(len(data)) < len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._saved["os.write"](fd, data)

    def _os_pwrite(self, fd, data, offset):
        if fd in self._fds and self._take(len(data)) < len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._saved["os.pwrite"](fd, data, offset)

    def _guard(self, name, nargs=1):
        real = self._saved[name]

        def call(*args, **kwargs):
            if self.mode == "readonly" and any(self._under(a, kwargs.get("dir_fd")) for a in args[:nargs]):
                raise self._erofs(args[0])
            return real(*args, **kwargs)

        return call

    # ------------------------------------------------------------------ install
    def install(self) -> FaultFS:
        self._saved = {"open": builtins.open, "os.open": os.open, "os.write": os.write, "os.pwrite": os.pwrite}
        for name in ("mkdir", "rmdir", "unlink", "remove", "replace", "rename", "link", "symlink", "truncate"):
            self._saved[name] = getattr(os, name)
        builtins.open = io.open = self._open
        os.open, os.write, os.pwrite = self._os_open, self._os_write, self._os_pwrite
        for name in ("mkdir", "rmdir", "unlink", "remove", "truncate"):
            setattr(os, name, self._guard(name))
        for name in ("replace", "rename", "link", "symlink"):
            setattr(os, name, self._guard(name, nargs=2))
        return self

    def uninstall(self) -> None:
        builtins.open = io.open = self._saved["open"]
        for key, fn in self._saved.items():
            if not key.startswith("open"):
                setattr(os, key.removeprefix("os."), fn)

    def __enter__(self) -> FaultFS:
        return self.install()

    def __exit__(self, *exc) -> None:
        self.uninstall()


def adarl_under_faults(root, mode: str, budget: int, args: list[str], **run_kwargs) -> subprocess.CompletedProcess:
    """Run ``adarl ARGS`` in a subprocess with :class:`FaultFS` over ``root`` (the CLI variant of a fault test)."""
    repo = Path(__file__).resolve().parents[1]
    env = {
        **os.environ,
        "PYTHONPATH": str(repo),
        "OMP_NUM_THREADS": "1",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }
    return subprocess.run(
        [sys.executable, __file__, str(root), mode, str(budget), "--", *args],
        env=env,
        capture_output=True,
        text=True,
        **run_kwargs,
    )


if __name__ == "__main__":  # python tests/faultfs.py ROOT MODE BUDGET -- ARGS...: `adarl ARGS` under FaultFS
    root, mode, budget, sep, *rest = sys.argv[1:]
    assert sep == "--"
    FaultFS(root, mode, int(budget)).install()
    from adarl.cli import main

    sys.exit(main(rest))
