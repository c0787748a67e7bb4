"""Divergence guards: stop (or roll back) a run as soon as a loss, gradient or parameter stops being finite.

One NaN in a SAC update spreads to every parameter within a few steps and a checkpoint written after it is
useless. :class:`NonFiniteGuard` checks, at every optimisation step, the losses (before ``backward``), the
gradients (before the optimiser step) and the parameters (after it), with one fused norm per group so the check
costs one host sync. :func:`check_live_layers` verifies that a rank event left every low-rank layer alive (finite,
non-zero factors of rank >= 1): two zero factors can never train again.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import torch

from adarl.errors import AdaRLError

__all__ = ["NonFiniteError", "DeadLayerError", "NonFiniteGuard", "check_live_layers"]


class NonFiniteError(AdaRLError):
    """A loss, gradient or parameter became NaN or infinite; ``what`` names it, ``stage`` says where."""

    def __init__(self, message: str, *, stage: str, what: str, update: int) -> None:
        super().__init__(message)
        self.stage, self.what, self.update = stage, what, update


class DeadLayerError(AdaRLError):
    """A rank event left a low-rank layer with a zero or non-finite factor."""


def _all_finite(tensors: list[torch.Tensor]) -> bool:
    if not tensors:
        return True
    # the max-abs norm: inf/nan anywhere in a tensor makes it non-finite, and it never overflows (the 2-norm of a
    # finite tensor above ~1.8e19 in float32 is inf: a finite parameter was reported non-finite, "...: ?")
    norms = torch._foreach_norm(tensors, float("inf"))
    return bool(torch.isfinite(torch.stack(norms)).all())


def _first_bad(named: Iterable[tuple[str, torch.Tensor]]) -> str:
    """The first tensor that is not finite, named, with what it holds; else the largest in magnitude (never "?")."""
    largest, top = None, -1.0
    for name, t in named:
        if t is None:
            continue
        if not bool(torch.isfinite(t).all()):
            kind = "nan" if bool(torch.isnan(t).any()) else "inf"
            return f"{name} ({kind})"
        peak = float(t.detach().abs().max()) if t.numel() else 0.0
        if peak > top:
            largest, top = name, peak
    return f"{largest} (the largest, |x| up to {top:.3g})" if largest is not None else "no tensor"


class NonFiniteGuard:
    """Checks one SAC update's losses, gradients and parameters; raises :class:`NonFiniteError` at the first bad one.

    ``params`` maps a readable name (``"actor.module.0.w1"``) to each trained tensor.
    """

    def __init__(self, params: Mapping[str, torch.Tensor]) -> None:
        self.params = dict(params)

    def _fail(self, stage: str, what: str, update: int) -> None:
        raise NonFiniteError(f"non-finite {stage} at update {update}: {what}", stage=stage, what=what, update=update)

    def check_losses(self, losses: Mapping[str, torch.Tensor], update: int) -> None:
        vals = [v.detach().reshape(()) for v in losses.values()]
        if not bool(torch.isfinite(torch.stack(vals)).all()):
            self._fail("loss", _first_bad((k, v.detach()) for k, v in losses.items()), update)

    def check_grads(self, update: int) -> None:
        grads = [p.grad for p in self.params.values() if p.grad is not None]
        if not _all_finite(grads):
            self._fail("gradient", _first_bad((k, p.grad) for k, p in self.params.items()), update)

    def check_params(self, update: int) -> None:
        if not _all_finite([p.detach() for p in self.params.values()]):
            self._fail("parameter", _first_bad((k, p.detach()) for k, p in self.params.items()), update)


def check_live_layers(named_factors: Mapping[str, torch.Tensor], event_step: int | None = None) -> None:
    """Every ``w1``/``w2`` factor finite, of rank >= 1 and non-zero (per member of a stacked Q ensemble)."""
    for name, t in named_factors.items():
        t = t.detach()
        where = f" after the rank event at step {event_step}" if event_step is not None else ""
        if 0 in t.shape[-2:]:
            raise DeadLayerError(f"layer factor {name} has rank 0{where} (shape {list(t.shape)})")
        if not bool(torch.isfinite(t).all()):
            raise DeadLayerError(f"layer factor {name} is not finite{where}")
        flat = t.reshape(-1, t.shape[-2] * t.shape[-1]) if t.dim() > 2 else t.reshape(1, -1)
        if bool((flat.abs().amax(dim=1) == 0).any()):
            raise DeadLayerError(f"layer factor {name} is all zero{where}: the layer could never train again")
