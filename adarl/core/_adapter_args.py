"""The checks of :class:`~adarl.core.adapter.RankAdapter`'s arguments, and their normal form.

Why apart: an argument that would fail at the first rank event, hours into a run (a scheduler that cannot restart,
a rule that measures without data), is refused when the adapter is built, each with a message that says what is
allowed; the adapter's constructor then only stores what this returns.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from adarl.core._sites import SCOPES
from adarl.core._surgery import TARGET_MODES
from adarl.core.acceptance import ProjectionAcceptance
from adarl.core.lowrank import is_integer
from adarl.core.lr_schedule import warmup_cosine_lambdas
from adarl.core.rank import RankRule
from adarl.errors import AdaRLValueError

__all__ = ["AdapterArgs", "check_adapter_args"]


@dataclass(frozen=True)
class AdapterArgs:
    """The adapter's arguments in normal form (lists, ints)."""

    optimizers: list
    interval: int
    scope: str
    min_rank: int
    target_mode: str
    lr_schedulers: list
    on_truncate: list
    on_event: list
    num_threads: int | None


def check_adapter_args(
    *,
    optimizers,
    rule: RankRule,
    interval: int,
    scope: str,
    min_rank: int,
    target_mode: str,
    lr_schedulers: Sequence,
    on_truncate: Sequence[Callable] | Callable,
    on_event: Sequence[Callable] | Callable,
    fit_data: Any,
    num_threads: int | None,
    acceptance: ProjectionAcceptance | None,
    log_step: Callable[[], int] | None,
) -> AdapterArgs:
    """Refuse, with :class:`~adarl.errors.AdaRLValueError`, what the adapter cannot work with; normalise the rest."""
    if num_threads is not None and (not is_integer(num_threads) or num_threads < 1):
        raise AdaRLValueError(f"num_threads must be an integer >= 1 or None (keep the process's), got {num_threads!r}")
    if not is_integer(interval) or interval < 1:
        raise AdaRLValueError(f"interval must be an integer >= 1 (optimisation steps between events), got {interval!r}")
    if scope not in SCOPES:
        raise AdaRLValueError(f"scope must be one of {list(SCOPES)}, got {scope!r}")
    if target_mode not in TARGET_MODES:
        raise AdaRLValueError(f"target_mode must be one of {list(TARGET_MODES)}, got {target_mode!r}")
    if not is_integer(min_rank) or min_rank < 1:
        raise AdaRLValueError(f"min_rank must be an integer >= 1, got {min_rank!r}")
    if log_step is not None and not callable(log_step):
        raise AdaRLValueError(
            f"log_step must be a callable returning the x-axis value (e.g. collected frames) or "
            f"None (the optimisation step), got {type(log_step).__name__}"
        )
    if not isinstance(rule, RankRule):
        raise AdaRLValueError(
            f"rule must be an adarl.core.rank.RankRule (e.g. EnergyRule(0.98)), got {type(rule).__name__}"
        )
    if isinstance(optimizers, torch.optim.Optimizer):
        optimizers = [optimizers]
    optimizers = list(optimizers)
    bad = [type(o).__name__ for o in optimizers if not isinstance(o, torch.optim.Optimizer)]
    if bad:
        raise AdaRLValueError(f"optimizers must be torch.optim.Optimizer instances, got {bad}")
    lr_schedulers = list(lr_schedulers)
    for sch in lr_schedulers:
        if not warmup_cosine_lambdas(sch) and not callable(getattr(sch, "restart", None)):
            raise AdaRLValueError(
                f"lr_schedulers must be LambdaLR schedulers with WarmupCosine lambdas (adarl.make_lr_scheduler) "
                f"or objects with a restart() method, got {type(sch).__name__}"
            )
    if callable(on_truncate):
        on_truncate = [on_truncate]
    on_truncate = list(on_truncate)
    for cb in on_truncate:
        if not callable(cb):
            raise AdaRLValueError(f"on_truncate entries must be callables fn(event), got {type(cb).__name__}")
    if callable(on_event):
        on_event = [on_event]
    on_event = list(on_event)
    for cb in on_event:
        if not callable(cb):
            raise AdaRLValueError(f"on_event entries must be callables fn(event), got {type(cb).__name__}")
    if acceptance is not None and not isinstance(acceptance, ProjectionAcceptance):
        raise AdaRLValueError(
            f"acceptance must be an adarl.ProjectionAcceptance or None (apply every candidate), "
            f"got {type(acceptance).__name__}"
        )
    for needs, what in (
        (rule.needs_fit, f"{type(rule).__name__} measures"),
        (acceptance is not None, "the acceptance step measures"),
    ):
        if needs and fit_data is None:
            raise AdaRLValueError(
                f"{what} the network's outputs: pass fit_data (a callable returning a TensorDict batch, e.g. "
                f"adarl.RecentTransitions(replay_buffer, 2048), or a replay buffer)"
            )
    if fit_data is not None and not callable(fit_data) and not callable(getattr(fit_data, "sample", None)):
        raise AdaRLValueError(f"fit_data must be a callable or a replay buffer, got {type(fit_data).__name__}")
    return AdapterArgs(
        optimizers=optimizers,
        interval=int(interval),
        scope=scope,
        min_rank=int(min_rank),
        target_mode=target_mode,
        lr_schedulers=lr_schedulers,
        on_truncate=on_truncate,
        on_event=on_event,
        num_threads=None if num_threads is None else int(num_threads),
    )
