"""Safe writes and reads of a run folder's files: nothing half-written, nothing unsafe loaded, every error named.

Behind :mod:`adarl.runtime.run_folder.run_dir` (its only user). Writes go to a temporary file, are fsync'ed and
renamed, so a
crash or a full disk mid-write leaves the previous file intact; a write that cannot fit is refused before it starts;
an ``OSError`` without a file name gets one. Loads accept regular files of tensors and plain containers only
(``torch.load(weights_only=True)``), and say in our words why a file was refused. An older checkpoint's replay
buffer (TorchRL's ``dumps()`` folder, which TorchRL reads with ``pickle.load`` and tensordict with imports by name)
is checked first to hold raw tensors and JSON only (:func:`check_dumps_folder`).
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import pickle
import pickletools
import re
import shutil
import stat
import sys
import warnings
from pathlib import Path

from adarl.errors import describe_os_error

__all__ = [
    "NotAFile",
    "UnsafeFile",
    "atomic_torch_save",
    "atomic_write_text",
    "buffer_nbytes",
    "check_dumps_folder",
    "check_free_space",
    "fsync_dir",
    "naming",
    "nbytes",
    "os_why",
    "plain",
    "safe_load",
    "why_unloadable",
]


def _is_tensor(obj) -> bool:
    """``isinstance(obj, torch.Tensor)`` without importing torch here: a process that made a tensor imported torch,
    and one that did not (an experiment's driver, a refused command) is spared torch's seconds of import."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(obj, torch.Tensor)


def plain(obj):
    """``obj`` as plain JSON values: tensors as lists, records as dicts, non-finite floats as None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if _is_tensor(obj):
        return plain(obj.tolist())
    if hasattr(obj, "as_dict"):
        return plain(obj.as_dict())
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        return plain(obj.item())
    if hasattr(obj, "__dict__"):
        return plain(vars(obj))
    return str(obj)


def os_why(err: OSError, path: Path) -> str:
    """:func:`describe_os_error`, without the file name when it is ``path`` (already in the message)."""
    if err.filename is not None and Path(os.fsdecode(err.filename)) == Path(path):
        err = OSError(err.errno, err.strerror)
    return describe_os_error(err)


class NotAFile(Exception):
    """A path to load that is not a regular file (a FIFO, a directory, a device): refused unread."""


def safe_load(path: Path):
    """``torch.load(weights_only=True)`` of a regular file only. A FIFO would block the reader forever (until
    something writes into it), a device could give endless bytes: such a path is refused before reading a byte
    (opened non-blocking, checked with ``fstat``, so the check is about the file read, not an earlier one)."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kinds = {stat.S_ISFIFO: "a FIFO", stat.S_ISDIR: "a directory", stat.S_ISSOCK: "a socket"}
            kind = next((k for test, k in kinds.items() if test(mode)), "a device")
            raise NotAFile(f"is not a regular file ({kind}); refused unread")
        fh = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with fh, warnings.catch_warnings():  # torch's pickle-protocol chatter about files it then refuses anyway
        warnings.simplefilter("ignore")
        import torch

        return torch.load(fh, map_location="cpu", weights_only=True)


class UnsafeFile(Exception):
    """A file that loading would run code from, or that its format never holds: refused unread (the message says
    which, relative to the folder checked)."""


# pickle opcodes that call or import something; a pickle without them is plain values and containers
_CALLING_OPCODES = {
    "GLOBAL", "STACK_GLOBAL", "REDUCE", "BUILD", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "EXT1", "EXT2", "EXT4",
    "PERSID", "BINPERSID",
}  # fmt: skip
# the classes a replay-buffer dump's meta.json may name (tensordict imports or unpickles anything else)
_DUMP_TYPES = {"<class 'tensordict._td.TensorDict'>", "<class 'tensordict.tensordict.TensorDict'>"}


def _check_plain_pickle(data: bytes, name: str) -> None:
    strings: list[str] = []
    try:
        for op, arg, _ in pickletools.genops(data):
            if op.name in _CALLING_OPCODES:
                called = str(arg).replace(" ", ".") if op.name == "GLOBAL" else ".".join(strings[-2:])
                what = f"a Python object ({called})" if called else "a Python object"
                raise UnsafeFile(f"{name} holds {what}, not plain values; refused unread, nothing in it ran")
            if isinstance(arg, str):
                strings.append(arg)
    except UnsafeFile:
        raise
    except Exception:  # noqa: BLE001 - not a pickle, or cut short
        raise UnsafeFile(f"{name} is corrupt or truncated (not a pickle of plain values)") from None


def _check_dump_meta(data: bytes, name: str) -> None:
    try:
        meta = json.loads(data)
    except ValueError:
        raise UnsafeFile(f"{name} is corrupt (not JSON)") from None
    if not isinstance(meta, dict) or meta.get("_type") not in _DUMP_TYPES:
        kind = meta.get("_type") if isinstance(meta, dict) else None
        raise UnsafeFile(f"{name} names the class {kind!r}, not a TensorDict (tensordict would import or unpickle it)")
    for key, entry in meta.items():
        if isinstance(entry, dict) and entry.get("type") not in (None, "TensorDict"):
            raise UnsafeFile(f"{name} holds {key!r} as {entry.get('type')!r}, not a tensor or a TensorDict")


def check_dumps_folder(folder: Path) -> None:
    """Refuse (:class:`UnsafeFile`) a TorchRL ``dumps()`` folder (an older checkpoint's replay buffer) that holds
    anything but what TorchRL reads as data: raw ``*.memmap`` tensors, JSON whose ``meta.json`` name TensorDicts
    only, and a top-level ``prefetch.pkl`` of plain values. TorchRL would ``pickle.load`` that file, ``torch.load``
    a ``transform.t``, and tensordict unpickle non-tensor leaves or import the class a ``meta.json`` names. Links,
    FIFOs and devices are refused too (a link could point anywhere, a FIFO block the reader). Nothing is run."""
    for path in sorted(folder.rglob("*")):
        name = path.relative_to(folder).as_posix()
        mode = path.lstat().st_mode
        if stat.S_ISDIR(mode):
            continue
        if not stat.S_ISREG(mode):
            raise UnsafeFile(f"{name} is not a regular file (a link, FIFO or device); refused unread")
        if path.suffix == ".memmap":
            continue
        if name == "prefetch.pkl":
            _check_plain_pickle(path.read_bytes(), name)
        elif path.name == "meta.json":
            _check_dump_meta(path.read_bytes(), name)
        elif path.suffix != ".json":
            raise UnsafeFile(
                f"{name} is not part of a replay buffer adarl wrote (raw tensors and JSON only); refused unread"
            )


def why_unloadable(err: Exception) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in our words: torch's own message advises retrying
    with ``weights_only=False``, which would run any code in the file, so it is never passed on."""
    text = str(err)
    if isinstance(err, NotAFile):
        return text.removeprefix("is ")
    if isinstance(err, EOFError) or not text.strip():
        return "it is empty or cut short (truncated)"
    if isinstance(err, pickle.UnpicklingError):
        found = re.search(r"GLOBAL ([\w.]+)", text)
        if found:
            return (
                f"it holds a Python object ({found.group(1)}), not only tensors and plain containers; refused "
                f"unread, nothing in it ran"
            )
        return "it is corrupt or not a torch checkpoint (only tensors and plain containers are accepted)"
    if "zip" in text.lower() or "PytorchStreamReader" in text:
        return "it is truncated or corrupt (its zip archive is incomplete)"
    return f"it is corrupt ({type(err).__name__})"


def buffer_nbytes(replay_buffer) -> int:
    """Bytes of a replay buffer's storage tensors (what its dump will take), 0 when unknown."""
    try:
        import torch

        data = replay_buffer._storage._storage
        leaves = [data] if isinstance(data, torch.Tensor) else data.values(include_nested=True, leaves_only=True)
        return sum(t.numel() * t.element_size() for t in leaves if isinstance(t, torch.Tensor))
    except Exception:  # noqa: BLE001 - an estimate only; the write itself still reports a full disk
        return 0


def nbytes(obj) -> int:
    """Bytes of the tensors in a (nested) state dict."""
    if _is_tensor(obj):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(nbytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(nbytes(v) for v in obj)
    return 0


def check_free_space(folder: Path, size: int, what: str) -> None:
    """Refuse before writing when ``what`` cannot fit (a clear message, nothing partial to clean up)."""
    margin = 64 << 10  # file headers, pickled containers, metadata
    free = shutil.disk_usage(folder).free
    if size + margin > free:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device ({what} needs {(size + margin) / 1e6:.1f} MB, {free / 1e6:.1f} MB free)",
            str(folder),
        )


@contextlib.contextmanager
def naming(path: Path):
    """An ``OSError`` without a file name (a full disk met by a buffered write's flush) gets ``path``: every disk
    error adarl reports names the file it could not write."""
    try:
        yield
    except OSError as err:
        if err.filename is not None:
            raise
        raise OSError(err.errno, err.strerror, str(path)) from None


def atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if isinstance(err, OSError) and err.filename == str(tmp):  # name the file the user knows
            raise OSError(err.errno, err.strerror, str(path)) from None
        raise


def atomic_torch_save(obj, path: Path) -> None:
    import torch

    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("wb") as fh:
            try:
                torch.save(obj, fh)
            except RuntimeError as err:
                # A failed write (ENOSPC) inside torch.save surfaces as torch's "unexpected pos" RuntimeError from
                # closing the zip; the OSError that caused it is its context: report that one.
                cause = err.__context__
                while cause is not None and not isinstance(cause, OSError):
                    cause = cause.__context__
                if cause is None:
                    raise
                raise cause from None
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
