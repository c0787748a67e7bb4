"""A rank event's side effects without the truncation: the control that separates AdaRL's restarts from its ranks.

An AdaRL event that changes a rank does two kinds of things: it truncates layers, and it *restarts* training around
them (the learning rate drops to zero and warms up again, App. D.1; the replay buffer is emptied and refilled with the
new policy, App. D.5.3). Full-rank SAC does neither, so "AdaRL against SAC" mixes both. :class:`ScheduledRestarts`
does only the second: every ``interval`` optimisation steps it restarts the LR schedules and runs the ``on_truncate``
callbacks (the warm start) exactly as :class:`~adarl.core.adapter.RankAdapter` does after an event that changed a
rank, and truncates nothing. It has the adapter's hook surface (``step``, ``adapt``, ``on_truncate``, ``on_event``,
``history``, ``ranks``, ``state_dict``), so whatever is registered on an adapter (e.g.
:class:`~adarl.runtime.rank_events.RankEventEffects`) registers on it unchanged. A recipe asks for it with
``rank.truncate: false`` (``recipes/baselines/<env>_sac_restarts.yaml``).

>>> import torch
>>> from adarl.core.lr_schedule import make_lr_scheduler
>>> optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], lr=1.0)
>>> scheduler = make_lr_scheduler(optimizer, warmup_steps=2)
>>> seen = []
>>> restarts = ScheduledRestarts(3, [scheduler], on_truncate=[lambda event: seen.append(event.step)])
>>> for _ in range(6):
...     optimizer.step()
...     scheduler.step()
...     _ = restarts.step()
>>> seen, optimizer.param_groups[0]["lr"]
([3, 6], 0.0)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from torch import nn

from adarl.core._sites import SiteRanks, find_low_rank_layers
from adarl.core.lr_schedule import restart_lr_scheduler, warmup_cosine_lambdas
from adarl.errors import AdaRLValueError

__all__ = ["RestartEvent", "ScheduledRestarts"]


@dataclass
class RestartEvent:
    """One restart: the optimisation step it ran at. It changes no layer (``layers`` is empty) but sets off what a
    rank change does, so ``changed`` is true: callbacks written for rank events run as they would after one."""

    step: int
    index: int
    layers: list = field(default_factory=list)
    adapter: Any = field(default=None, repr=False, compare=False)
    changed: bool = True

    @property
    def ranks(self) -> dict[str, int]:
        return {}

    def as_dict(self) -> dict:
        return {"step": self.step, "index": self.index, "layers": [], "restart": True}


def _callbacks(name: str, value) -> list[Callable]:
    value = [value] if callable(value) else list(value)
    for cb in value:
        if not callable(cb):
            raise AdaRLValueError(f"ScheduledRestarts: {name} entries must be callables fn(event), got {cb!r}")
    return value


class ScheduledRestarts(SiteRanks):
    """Every ``interval`` optimisation steps: restart the LR schedules, then run ``on_truncate`` and ``on_event``.

    Args:
        interval: optimisation steps between restarts (a recipe's ``rank.interval``: AdaRL's events fall there).
        lr_schedulers: schedulers to restart; a ``LambdaLR`` of :class:`~adarl.core.lr_schedule.WarmupCosine`
            restarts its warm-up (learning rate 0 now), any other scheduler needs a ``restart()`` method.
        on_truncate: callables ``fn(event)`` run at every restart, as a rank adapter runs them after an event that
            changed a rank (e.g. :class:`~adarl.core.warmstart.ReplayWarmStart`).
        on_event: callables ``fn(event)`` run after them (records, logs).
        loss_module: the loss whose ``LowRankLinear`` layers (if any) :attr:`ranks` reports: a factorised network
            trained with restarts alone (issue 34's ``factorised_restarts``) keeps its full ranks, and logs, eval.csv
            and summary.json say so instead of showing no ranks. Its layers are never changed.

    Call :meth:`step` after every optimisation step (or register it: :meth:`register`).
    """

    def __init__(
        self,
        interval: int,
        lr_schedulers: Sequence = (),
        *,
        on_truncate: Sequence[Callable] | Callable = (),
        on_event: Sequence[Callable] | Callable = (),
        loss_module: nn.Module | None = None,
    ) -> None:
        if isinstance(interval, bool) or not isinstance(interval, int) or interval < 1:
            raise AdaRLValueError(f"ScheduledRestarts: interval must be an integer >= 1, got {interval!r}")
        for sch in lr_schedulers:
            if not warmup_cosine_lambdas(sch) and not callable(getattr(sch, "restart", None)):
                raise AdaRLValueError(
                    f"ScheduledRestarts: {type(sch).__name__} cannot restart: give a LambdaLR of WarmupCosine "
                    "(adarl.make_lr_scheduler) or a scheduler with a restart() method"
                )
        self.interval = int(interval)
        self.lr_schedulers = list(lr_schedulers)
        self.on_truncate = _callbacks("on_truncate", on_truncate)
        self.on_event = _callbacks("on_event", on_event)
        self.step_count = 0
        self.history: list[RestartEvent] = []
        # the rank adapter's read-only views (SiteRanks) over these: a restart keeps every rank
        self.sites = find_low_rank_layers(loss_module, "both")[0] if loss_module is not None else []

    def step(self) -> RestartEvent | None:
        """Count one optimisation step; every ``interval`` steps restart (:meth:`adapt`) and return the event."""
        self.step_count += 1
        if self.step_count % self.interval == 0:
            return self.adapt()
        return None

    __call__ = step

    def register(self, trainer, name: str = "restarts") -> None:
        """Register :meth:`step` at a TorchRL trainer's ``"post_optim"`` stage and this object as a module."""
        trainer.register_op("post_optim", self.step)
        trainer.register_module(name, self)

    def adapt(self) -> RestartEvent:
        """Restart now (named as the adapter's method, so a loop that forces an event calls either)."""
        event = RestartEvent(step=self.step_count, index=len(self.history))
        for cb in self.on_truncate:
            check = getattr(cb, "check_event", None)
            if callable(check):
                check(event)
        self.history.append(event)
        for sch in self.lr_schedulers:
            if warmup_cosine_lambdas(sch):
                restart_lr_scheduler(sch)
            else:
                sch.restart()
        for cb in self.on_truncate:
            cb(event)
        for cb in self.on_event:
            cb(event)
        return event

    def state_dict(self) -> dict:
        return {"step_count": self.step_count, "restarts": [e.step for e in self.history]}

    def load_state_dict(self, state: dict) -> None:
        if not isinstance(state, dict) or "step_count" not in state or "restarts" not in state:
            raise AdaRLValueError(
                f"ScheduledRestarts.load_state_dict: expected the keys 'step_count' and 'restarts', got {state!r:.200}"
            )
        self.step_count = int(state["step_count"])
        self.history = [RestartEvent(step=int(s), index=i) for i, s in enumerate(state["restarts"])]

    def __repr__(self) -> str:
        return (
            f"ScheduledRestarts(interval={self.interval}, step_count={self.step_count}, restarts={len(self.history)})"
        )
