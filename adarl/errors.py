"""The project's exceptions: one base class so callers (and the CLI) can catch exactly our validation errors."""

from __future__ import annotations

import errno

__all__ = ["AdaRLError", "AdaRLValueError", "RecipeError", "CheckpointError", "AdaRLWarning",
           "CheckpointFallbackWarning", "STORAGE_ERRNOS", "describe_os_error"]


class AdaRLError(Exception):
    """Base class of every error adarl raises on purpose."""


class AdaRLValueError(AdaRLError, ValueError):
    """A value out of range or of the wrong kind; the message names the value and what is allowed."""


class RecipeError(AdaRLValueError):
    """A recipe (file or overrides) that does not validate; the message names the key, value and allowed values."""


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
STORAGE_ERRNOS = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota exceeded", errno.EROFS: "read-only file system",
                  errno.EACCES: "no permission", errno.EPERM: "no permission", errno.EIO: "input/output error"}


def describe_os_error(err: OSError) -> str:
    """One line for a failed file operation: the file, and why in plain words (``'/x/f.csv': No space left...``)."""
    why = err.strerror or str(err)
    hint = STORAGE_ERRNOS.get(err.errno)
    if hint and hint.lower() != why.lower():
        why += f" ({hint})"
    return f"{str(err.filename)!r}: {why}" if err.filename else why
