"""One optimisation step, behind one interface: TorchRL's ``SACLoss`` step or the fused one (SAC), TD3's step with
delayed actor updates (:class:`DelayedActorStep`, the ``td3`` loop).

:func:`~adarl.runtime.builders.sac.build_sac_components` picks the step (``algorithm.fused``) and the trainer calls it,
whichever it is: ``losses = components.update(guard, update=n)``. Both sample a batch from the replay buffer
(the same indices from the same generator), compute SAC's three losses, back-propagate, clip, step the optimisers
and LR schedules and update the target critics; both return the detached loss values by name. The divergence
guard (:class:`~adarl.runtime.guards.NonFiniteGuard`), when given, checks the losses, gradients and parameters
at the points each step can reach.
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.objectives import SoftUpdate

from adarl.errors import AdaRLValueError
from adarl.fast.replay import UniformTensorSampler
from adarl.fast.sac import FusedSACUpdate
from adarl.runtime.guards import NonFiniteGuard

__all__ = [
    "UpdateStep",
    "LossStep",
    "FusedStep",
    "DelayedActorStep",
    "delayed_optimisation",
    "loss_output",
    "require_losses",
    "scalar_entries",
    "SAC_LOSSES",
]

#: the losses every SAC step checks and returns (with ``alpha``, and ``loss_<term>`` per loss term)
SAC_LOSSES = ("loss_actor", "loss_qvalue", "loss_alpha")


def loss_output(
    loss: nn.Module, batch: TensorDictBase, terms: Mapping[str, nn.Module]
) -> tuple[TensorDictBase, dict[str, torch.Tensor]]:
    """``loss(batch)`` with each term's ``loss_<name>`` added (``term.wrap_output``), and its ``loss_*`` entries:
    TorchRL's convention sums every one (a registered algorithm's own included); the other entries are metrics."""
    td = loss(batch)
    for term in terms.values():
        td = term.wrap_output(td)
    return td, {k: td[k] for k in td.keys() if isinstance(k, str) and k.startswith("loss_")}


def require_losses(losses: Mapping[str, torch.Tensor], required: Sequence[str], loss: nn.Module, loop: str) -> None:
    """Refuse a loss whose output lacks one of the ``loss_*`` entries the ``loop`` steps (a plugin's loss, say)."""
    missing = [k for k in required if k not in losses]
    if missing:
        raise AdaRLValueError(
            f"{type(loss).__name__}'s output lacks {missing}; a loss on the {loop} loop returns "
            f"{list(required)} (and may add more loss_* entries and metrics)"
        )


def scalar_entries(td: TensorDictBase) -> dict[str, torch.Tensor]:
    """A loss output's scalar floating entries, detached: the losses and metrics a step returns by name."""
    return {
        k: v.detach()
        for k, v in td.items()
        if isinstance(k, str) and isinstance(v, torch.Tensor) and v.numel() == 1 and v.is_floating_point()
    }


class UpdateStep(ABC):
    """One optimisation step: sample, losses, backward, clipping, optimisers, LR schedules, target update.

    ``step(guard, update=n)`` (a call) returns the detached losses by name; :meth:`on_rank_event` is an ``on_truncate``
    callback of the rank adapter (the parameters changed shape in place)."""

    @abstractmethod
    def __call__(self, guard: NonFiniteGuard | None = None, *, update: int = 0) -> dict[str, torch.Tensor]:
        """One step; ``guard`` (when given) checks it, ``update`` is the step's index in its messages."""

    def on_rank_event(self, event=None) -> None:  # noqa: B027 (optional: a step that holds no shapes needs none)
        """The parameters changed shape in place (a rank event): re-bind what depends on the shapes."""


class LossStep(UpdateStep):
    """The step with TorchRL's pieces: ``loss(rb.sample())``, ``backward()``, per-optimiser gradient clipping,
    ``opt.step()``, the schedulers, then ``SoftUpdate.step()``.

    ``terms``: loss terms (``{name: term}``, e.g. the Parseval regulariser) whose ``wrap_output(td)`` adds
    ``loss_<name>`` to the loss's output. As TorchRL's trainers do, every ``loss_*`` entry of the output is added
    to the total; every scalar entry (losses and metrics, a registered loss's own included) is returned."""

    def __init__(
        self,
        loss: nn.Module,
        optimizers: Sequence[torch.optim.Optimizer],
        *,
        replay_buffer: TensorDictReplayBuffer,
        target_updater: SoftUpdate,
        schedulers: Sequence = (),
        max_grad_norm: float | None = None,
        terms: Mapping[str, nn.Module] | None = None,
    ) -> None:
        self.loss, self.optimizers, self.schedulers = loss, list(optimizers), list(schedulers)
        self.replay_buffer, self.target_updater = replay_buffer, target_updater
        self.max_grad_norm, self.terms = max_grad_norm, dict(terms or {})

    def __call__(self, guard: NonFiniteGuard | None = None, *, update: int = 0) -> dict[str, torch.Tensor]:
        td, losses = loss_output(self.loss, self.replay_buffer.sample(), self.terms)
        require_losses(losses, SAC_LOSSES, self.loss, "SAC")
        if guard is not None:
            guard.check_losses(losses, update)
        total = sum(losses.values())
        total.backward()
        if guard is not None:
            guard.check_grads(update)
        if self.max_grad_norm is not None:
            for opt in self.optimizers:
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], self.max_grad_norm)
        for opt in self.optimizers:
            opt.step()
            opt.zero_grad(set_to_none=True)
        for sched in self.schedulers:
            sched.step()
        self.target_updater.step()
        if guard is not None:
            guard.check_params(update)
        return scalar_entries(td)


class FusedStep(UpdateStep):
    """The same step on plain tensors: a :class:`~adarl.fast.replay.UniformTensorSampler` draws the indices
    ``rb.sample()`` would draw and :class:`~adarl.fast.sac.FusedSACUpdate` computes the step (no gradient check:
    the manual backward never materialises a graph to check; the losses and parameters are checked)."""

    def __init__(
        self, update: FusedSACUpdate, replay_buffer: TensorDictReplayBuffer, generator: torch.Generator | None = None
    ) -> None:
        self.fused = update
        self.sampler = UniformTensorSampler(replay_buffer, update.keys, generator=generator)

    def __call__(self, guard: NonFiniteGuard | None = None, *, update: int = 0) -> dict[str, torch.Tensor]:
        out = self.fused.step(*self.sampler())
        if guard is not None:
            guard.check_losses({k: v for k, v in out.items() if k.startswith("loss_")}, update)
            guard.check_params(update)
        return out

    def on_rank_event(self, event=None) -> None:
        self.fused.on_rank_event(event)


def delayed_optimisation(step, losses: dict, stepped: list, guard: NonFiniteGuard | None, update: int) -> None:
    """What a delayed-policy step (TD3's, TQC/CrossQ/REDQ's) does with its losses: backward of their sum (the guard's
    checks around it), per-optimiser gradient clipping (``step.max_grad_norm``), the ``stepped`` optimisers, every
    gradient cleared, and every LR schedule stepped (each update, though a delayed optimiser steps only every k-th:
    torch's warning about a schedule stepped before its optimiser says nothing here)."""
    if guard is not None:
        guard.check_losses(losses, update)
    sum(losses.values()).backward()
    if guard is not None:
        guard.check_grads(update)
    if step.max_grad_norm is not None:
        for opt in stepped:
            for group in opt.param_groups:
                torch.nn.utils.clip_grad_norm_(group["params"], step.max_grad_norm)
    for opt in stepped:
        opt.step()
    for opt in step.optimizers.values():
        opt.zero_grad(set_to_none=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler.step\(\)` before")
        for sched in step.schedulers:
            sched.step()


class DelayedActorStep(UpdateStep):
    """TD3's step with TorchRL's pieces (TorchRL's TD3 example, one loss call): ``loss(rb.sample())``, backward of
    the sum of its ``loss_*`` entries, per-optimiser gradient clipping, the critic's optimiser every step, the actor's
    and ``SoftUpdate.step()`` (target actor and critics) every ``policy_update_delay``-th step (``update + 1`` a
    multiple of it, as TorchRL's example counts), the LR schedules every step.

    The loss's actor loss reads the critics through detached parameters and its value loss the target actor, so
    one backward of the sum gives each network its own gradient (TD3Loss's, DDPGLoss's ``separate_losses``
    convention); the actor's gradient of an off step is dropped. Its output must hold ``loss_actor`` and a critic
    loss (``loss_qvalue``, TD3; ``loss_value``, DDPG); every scalar entry is returned. ``terms``: as
    :class:`LossStep`'s."""

    CRITIC_LOSSES = ("loss_qvalue", "loss_value")

    def __init__(
        self,
        loss: nn.Module,
        optimizers: Mapping[str, torch.optim.Optimizer],
        *,
        replay_buffer: TensorDictReplayBuffer,
        target_updater: SoftUpdate,
        policy_update_delay: int = 2,
        schedulers: Sequence = (),
        max_grad_norm: float | None = None,
        terms: Mapping[str, nn.Module] | None = None,
    ) -> None:
        if set(optimizers) != {"actor", "critic"}:
            raise AdaRLValueError(
                f"DelayedActorStep needs the optimisers 'actor' and 'critic', got {sorted(optimizers)}"
            )
        self.loss, self.optimizers, self.schedulers = loss, dict(optimizers), list(schedulers)
        self.replay_buffer, self.target_updater = replay_buffer, target_updater
        self.delay, self.max_grad_norm, self.terms = int(policy_update_delay), max_grad_norm, dict(terms or {})

    def updates_actor(self, update: int) -> bool:
        """Whether step ``update`` (0-based) steps the actor and the targets."""
        return (update + 1) % self.delay == 0

    def __call__(self, guard: NonFiniteGuard | None = None, *, update: int = 0) -> dict[str, torch.Tensor]:
        td, losses = loss_output(self.loss, self.replay_buffer.sample(), self.terms)
        if "loss_actor" not in losses or not any(k in losses for k in self.CRITIC_LOSSES):
            raise AdaRLValueError(
                f"{type(self.loss).__name__}'s output has {sorted(losses)}; a loss on the td3 loop returns "
                f"'loss_actor' and 'loss_qvalue' (TD3Loss) or 'loss_value' (DDPGLoss), and may add more loss_* "
                "entries and metrics"
            )
        actor_too = self.updates_actor(update)
        stepped = [self.optimizers["critic"]] + ([self.optimizers["actor"]] if actor_too else [])
        delayed_optimisation(self, losses, stepped, guard, update)
        if actor_too:
            self.target_updater.step()
        if guard is not None:
            guard.check_params(update)
        return scalar_entries(td)
