"""The project's exceptions: one base class so callers (and the CLI) can catch exactly our validation errors."""

from __future__ import annotations

import difflib
import errno
from collections.abc import Iterable
from typing import Any

__all__ = [
    "AdaRLError",
    "AdaRLValueError",
    "RecipeError",
    "MissingExtraError",
    "CheckpointError",
    "AdaRLWarning",
    "CheckpointFallbackWarning",
    "STORAGE_ERRNOS",
    "describe_os_error",
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


class MissingExtraError(AdaRLValueError):
    """What was asked for needs an optional extra that is not installed (wandb, tensorboard, ray, submitit,
    moviepy): bad input, like any other (the ``adarl`` command exits 2); the message names the ``pip install``."""


class CheckpointError(AdaRLError):
    """A checkpoint that is missing, corrupt, truncated, from a newer version or incompatible with the model.

    ``path`` is the refused file and ``reason`` the short why (both None where no single file is meant)."""

    def __init__(self, message: str, *, path=None, reason: str | None = None) -> None:
        super().__init__(message)
        self.path, self.reason = path, reason


class AdaRLWarning(UserWarning):
    """Base class of adarl's warnings; the ``adarl`` command prints each as one ``adarl: warning:`` line."""


class CheckpointFallbackWarning(AdaRLWarning):
    """A checkpoint was skipped (damaged, or written for another recipe) and an older one is used instead."""


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
    """
    opts = [str(o) for o in options]
    match = difflib.get_close_matches(str(word), opts, n=1, cutoff=0.6)
    if not match:  # case-only typos ('hopper-v5') score low in difflib
        match = [o for o in opts if o.lower() == str(word).lower()][:1]
    return f"; did you mean {match[0]!r}?" if match else ""
