"""The project's exceptions: one base class so callers (and the CLI) can catch exactly our validation errors."""

from __future__ import annotations

import difflib
import errno
import os
import shlex
from collections.abc import Iterable
from typing import Any

__all__ = [
    "AdaRLError",
    "AdaRLValueError",
    "RecipeError",
    "UnknownNameError",
    "MissingExtraError",
    "CheckpointError",
    "ExportFileError",
    "AdaRLWarning",
    "CheckpointFallbackWarning",
    "TorchFallbackWarning",
    "FusedFallbackWarning",
    "STORAGE_ERRNOS",
    "describe_os_error",
    "describe_name_too_long",
    "is_storage_failure",
    "command",
    "NO_VALUE",
    "one_of",
    "did_you_mean",
]


class AdaRLError(Exception):
    """Base class of every error adarl raises on purpose."""


class AdaRLValueError(AdaRLError, ValueError):
    """A value out of range or of the wrong kind; the message names the value and what is allowed."""


class RecipeError(AdaRLValueError):
    """A recipe (file or overrides) that does not validate; the message names the key, value and allowed values."""


class UnknownNameError(AdaRLValueError):
    """A name no registry entry has (an algorithm, a rank rule, an env id, ...); the message lists the allowed names.

    ``kind`` is what a name is called (``"algorithm.name"``), ``name`` the unknown one, ``allowed`` the registered
    names and ``hint`` how to register one (as the message ends it, or ``""``): a caller rewords the message from
    these, never by parsing it."""

    def __init__(self, message: str, *, kind: str, name: Any, allowed: Iterable[str], hint: str = "") -> None:
        super().__init__(message)
        self.kind, self.name, self.allowed, self.hint = kind, name, tuple(allowed), hint


class MissingExtraError(AdaRLValueError):
    """What was asked for needs an optional extra that is not installed (wandb, tensorboard, ray, submitit,
    moviepy): bad input, like any other (the ``adarl`` command exits 2); the message names the ``pip install``."""


class CheckpointError(AdaRLError):
    """A checkpoint that is missing, corrupt, truncated, from a newer version or incompatible with the model.

    ``path`` is the refused file and ``reason`` the short why (both None where no single file is meant)."""

    def __init__(self, message: str, *, path=None, reason: str | None = None) -> None:
        super().__init__(message)
        self.path, self.reason = path, reason


class ExportFileError(AdaRLValueError):
    """An exported policy file (``adarl export``) that is not one, or is empty, truncated, corrupt, changed since it
    was exported, or holds something that loading would run; nothing in a refused file was run.

    ``path`` is the refused file and ``reason`` the short why."""

    def __init__(self, message: str, *, path=None, reason: str | None = None) -> None:
        super().__init__(message)
        self.path, self.reason = path, reason


class AdaRLWarning(UserWarning):
    """Base class of adarl's warnings; the ``adarl`` command prints each as one ``adarl: warning:`` line."""


class CheckpointFallbackWarning(AdaRLWarning):
    """A checkpoint was skipped (damaged, or written for another recipe) and an older one is used instead."""


class TorchFallbackWarning(AdaRLWarning):
    """The installed torch is not one :mod:`adarl.fast`'s private kernels were tested on: its public paths are used."""


class FusedFallbackWarning(AdaRLWarning):
    """A registered algorithm's ``SACLoss`` runs TorchRL's (slower) path instead of the fused update, and why (said
    when a run that trains is built; a run loaded to evaluate does no update and does not say it)."""


# Failures of the file system rather than of adarl: the CLI reports these in one line instead of a traceback.
STORAGE_ERRNOS = {
    errno.ENOSPC: "disk full",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "no permission",
    errno.EPERM: "no permission",
    errno.EIO: "input/output error",
}


def describe_os_error(err: OSError) -> str:
    """One line for a failed file operation: the file, and why in plain words (``'/x/f.csv': No space left...``)."""
    why = err.strerror or str(err)
    hint = STORAGE_ERRNOS.get(err.errno)
    if hint and hint.lower() != why.lower():
        why += f" ({hint})"
    return f"{str(err.filename)!r}: {why}" if err.filename else why


def is_storage_failure(message: str) -> bool:
    """Whether a failure's message (a run's last line, an error's text) says the file system failed, not the work:
    a full disk, a quota, a read-only or failing disk, no permission (:data:`STORAGE_ERRNOS`, as
    :func:`describe_os_error` and ``OSError`` word them). Such a failure is worth retrying once it is fixed."""
    text = message.lower()
    return any(
        os.strerror(code).lower() in text or hint in text or f"[errno {code}]" in text
        for code, hint in STORAGE_ERRNOS.items()
    )


def command(*words) -> str:
    """A command to paste into a shell, each word quoted as the shell needs (``shlex.join``): a suggested command
    never runs more than it says, whatever a folder is named (``'a b;rm -rf x'`` stays one argument).

    >>> command("adarl", "resume", "runs/a b;rm -rf x")
    "adarl resume 'runs/a b;rm -rf x'"
    """
    return shlex.join(os.fspath(w) if isinstance(w, os.PathLike) else str(w) for w in words)


def _limit(path: str, name: str, default: int) -> int:
    """The file system's ``pathconf`` limit ``name`` where ``path`` (or its nearest existing parent) lives."""
    here = os.path.abspath(path or ".")
    while True:
        try:
            return int(os.pathconf(here, name))
        except (OSError, ValueError, AttributeError):
            parent = os.path.dirname(here)
            if parent == here:
                return default
            here = parent


def describe_name_too_long(err: OSError) -> str:
    """One line for ``ENAMETOOLONG`` (errno 36): a name given that the file system cannot hold, which is bad input,
    not a failing disk. Names the offending file or folder name and the limit (255 bytes a name, 4096 a path, on
    Linux's file systems)."""
    path = os.fsdecode(err.filename) if err.filename is not None else ""
    name_max = _limit(path, "PC_NAME_MAX", 255)
    long_names = [part for part in path.split(os.sep) if len(os.fsencode(part)) > name_max]
    if long_names:
        part = long_names[0]
        shown = part if len(part) <= 40 else f"{part[:40]}..."
        return (
            f"a name in the path {path.replace(part, shown)!r} is too long: {shown!r} is {len(os.fsencode(part))} "
            f"bytes, and a file or "
            f"folder name may have at most {name_max} bytes on this file system; choose a shorter name"
        )
    path_max = _limit(path, "PC_PATH_MAX", 4096)
    return (
        f"the path {path if len(path) <= 100 else path[:60] + '...' + path[-40:]!r} is too long "
        f"({len(os.fsencode(path))} bytes; at most {path_max} bytes on this file system); choose a shorter path"
        if path
        else f"a file name is too long (at most {name_max} bytes a name on this file system): {err.strerror or err}"
    )


#: The value of a problem about a key that has none (a required key that is missing): messages show no value.
NO_VALUE: Any = type("NoValue", (), {"__repr__": lambda self: "<no value>"})()


def one_of(options: Iterable[Any]) -> str:
    """The allowed values as an error message lists them: ``'a', 'b', 'c'``.

    >>> one_of(["sinusoid", "uniform"])
    "'sinusoid', 'uniform'"
    """
    return ", ".join(repr(o) for o in options)


def did_you_mean(word: str, options: Iterable[Any]) -> str:
    """``"; did you mean 'x'?"`` for the option closest to a mistyped ``word``, or ``""`` when none is close.

    >>> did_you_mean("unifrom", ["sinusoid", "uniform"])
    "; did you mean 'uniform'?"
    >>> did_you_mean("torso", ["foot_length", "torso_length"])
    "; did you mean 'torso_length'?"
    """
    opts = [str(o) for o in options]
    match = difflib.get_close_matches(str(word), opts, n=1, cutoff=0.6)
    if not match:  # case-only typos ('hopper-v5') score low in difflib
        match = [o for o in opts if o.lower() == str(word).lower()][:1]
    if not match and len(str(word)) >= 3:  # a name's start ('torso' for 'torso_length') scores low too
        match = sorted((o for o in opts if o.lower().startswith(str(word).lower())), key=len)[:1]
    return f"; did you mean {match[0]!r}?" if match else ""
