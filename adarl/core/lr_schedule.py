"""A restartable warm-up + cosine learning-rate schedule (paper App. D.1; ReLoRA's "jagged cosine").

The paper: "upon each reset, we set the learning rate to zero, gradually warm it up to the target value over 2000
steps, and then resume following the cosine schedule". :class:`WarmupCosine` is that schedule as a callable
*object* for :class:`torch.optim.lr_scheduler.LambdaLR`::

    factor(step) = ramp(step) * cosine(step)
    ramp(step)   = clamp((step - last_restart) / warmup_steps, 0, 1)        # 1 if warmup_steps == 0
    cosine(step) = min_factor + (1 - min_factor) * (1 + cos(pi * min(step, total_steps) / total_steps)) / 2
                   (1 when total_steps is None: constant after the warm-up)

The cosine runs over the *global* step, so a restart only multiplies it by a fresh warm-up ramp: the learning rate
drops to zero at the restart and climbs back to where the global cosine is by then. ``last_restart`` starts at 0,
so the very first steps warm up too (the usual warm-up + cosine).

Because :class:`~torch.optim.lr_scheduler.LambdaLR` saves the ``__dict__`` of callable objects in its
``state_dict()``, the restart point and the restart count are checkpointed with the scheduler for free.
"""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR

from adarl.errors import AdaRLValueError

__all__ = ["WarmupCosine", "make_lr_scheduler", "restart_lr_scheduler", "warmup_cosine_lambdas"]


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise AdaRLValueError(f"WarmupCosine: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


class WarmupCosine:
    """``step -> factor`` for :class:`~torch.optim.lr_scheduler.LambdaLR`: warm-up ramp times a global cosine.

    Args:
        warmup_steps: steps for the ramp from 0 to 1 after the start and after every :meth:`restart` (paper: 2000).
            ``0`` disables the ramp (then a restart does not change the learning rate).
        total_steps: length of the global cosine; ``None`` keeps the factor at 1 after the warm-up.
        min_factor: the cosine's floor, reached at ``total_steps`` and kept afterwards.

    >>> optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], lr=1e-3)
    >>> scheduler = make_lr_scheduler(optimizer, warmup_steps=4)  # one WarmupCosine per parameter group
    >>> lrs = []
    >>> for _ in range(5):
    ...     optimizer.step()
    ...     scheduler.step()
    ...     lrs.append(round(optimizer.param_groups[0]["lr"], 6))
    >>> lrs
    [0.00025, 0.0005, 0.00075, 0.001, 0.001]
    >>> restart_lr_scheduler(scheduler)  # after a rank event (RankAdapter does it): the warm-up starts again
    >>> optimizer.param_groups[0]["lr"]
    0.0
    """

    def __init__(self, warmup_steps: int = 2000, total_steps: int | None = None, min_factor: float = 0.0) -> None:
        self.warmup_steps = _check_int("warmup_steps", warmup_steps, 0)
        self.total_steps = None if total_steps is None else _check_int("total_steps", total_steps, 1)
        if isinstance(min_factor, bool) or not isinstance(min_factor, (int, float)) or not 0.0 <= min_factor <= 1.0:
            raise AdaRLValueError(f"WarmupCosine: min_factor must be a number in [0, 1], got {min_factor!r}")
        self.min_factor = float(min_factor)
        self.last_restart = 0
        self.restarts = 0

    def cosine(self, step: int) -> float:
        """The global cosine factor at ``step`` (without the warm-up ramp)."""
        if self.total_steps is None:
            return 1.0
        progress = min(max(step, 0), self.total_steps) / self.total_steps
        return self.min_factor + (1.0 - self.min_factor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    def ramp(self, step: int) -> float:
        """The warm-up factor at ``step``: 0 at the last restart, 1 after ``warmup_steps`` more steps."""
        if self.warmup_steps == 0:
            return 1.0
        return min(max((step - self.last_restart) / self.warmup_steps, 0.0), 1.0)

    def __call__(self, step: int) -> float:
        return self.ramp(step) * self.cosine(step)

    def restart(self, step: int) -> None:
        """Start a new warm-up at ``step`` (the scheduler's ``last_epoch``): the factor is 0 there."""
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise AdaRLValueError(f"WarmupCosine.restart: step must be an integer >= 0, got {step!r}")
        self.last_restart = int(step)
        self.restarts += 1

    def __repr__(self) -> str:
        return (
            f"WarmupCosine(warmup_steps={self.warmup_steps}, total_steps={self.total_steps}, "
            f"min_factor={self.min_factor}, last_restart={self.last_restart}, restarts={self.restarts})"
        )


def make_lr_scheduler(
    optimizer: torch.optim.Optimizer,
    warmup_steps: int = 2000,
    total_steps: int | None = None,
    min_factor: float = 0.0,
) -> LambdaLR:
    """A :class:`~torch.optim.lr_scheduler.LambdaLR` with one :class:`WarmupCosine` per parameter group.

    Call ``scheduler.step()`` after every ``optimizer.step()``. At construction the learning rate is already
    ``base_lr * factor(0)`` (0 with a warm-up), as with any ``LambdaLR``.
    """
    lambdas = [WarmupCosine(warmup_steps, total_steps, min_factor) for _ in optimizer.param_groups]
    return LambdaLR(optimizer, lambdas)


def warmup_cosine_lambdas(scheduler) -> list[WarmupCosine]:
    """The :class:`WarmupCosine` objects inside a ``LambdaLR`` (empty list if there are none)."""
    seen, out = set(), []
    for fn in getattr(scheduler, "lr_lambdas", ()):
        if isinstance(fn, WarmupCosine) and id(fn) not in seen:
            seen.add(id(fn))
            out.append(fn)
    return out


def restart_lr_scheduler(scheduler: LambdaLR) -> None:
    """Restart every :class:`WarmupCosine` of ``scheduler`` at its current step and apply the new rate now.

    The parameter groups' ``lr`` is set to ``base_lr * factor(last_epoch)`` right away (0 with a warm-up), so the
    next optimiser step already uses it; ``scheduler.step()`` then continues the ramp. Raises
    :class:`~adarl.errors.AdaRLValueError` when the scheduler holds no :class:`WarmupCosine`.
    """
    lambdas = warmup_cosine_lambdas(scheduler)
    if not lambdas:
        raise AdaRLValueError(
            f"restart_lr_scheduler needs a torch.optim.lr_scheduler.LambdaLR built with WarmupCosine lambdas "
            f"(see adarl.make_lr_scheduler), got {type(scheduler).__name__}"
        )
    step = int(scheduler.last_epoch)
    for fn in lambdas:
        fn.restart(step)
    lrs = []
    for group, base_lr, fn in zip(scheduler.optimizer.param_groups, scheduler.base_lrs, scheduler.lr_lambdas):
        lr = base_lr * fn(step)
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr
        lrs.append(lr)
    scheduler._last_lr = lrs
