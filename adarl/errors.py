"""The project's exceptions: one base class so callers (and the CLI) can catch exactly our validation errors."""

from __future__ import annotations

__all__ = ["AdaRLError", "AdaRLValueError", "RecipeError", "CheckpointError"]


class AdaRLError(Exception):
    """Base class of every error adarl raises on purpose."""


class AdaRLValueError(AdaRLError, ValueError):
    """A value out of range or of the wrong kind; the message names the value and what is allowed."""


class RecipeError(AdaRLValueError):
    """A recipe (file or overrides) that does not validate; the message names the key, value and allowed values."""


class CheckpointError(AdaRLError):
    """A checkpoint that is missing, corrupt, truncated, from a newer version or incompatible with the model."""
