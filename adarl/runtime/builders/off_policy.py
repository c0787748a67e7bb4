"""What every off-policy family builds the same way (SAC, TD3/DDPG, a family of your own): the skeleton of its
builder (:func:`build_off_policy_components`), the LR schedules, the replay buffer, the collector, the rank adapter
with its acceptance step, the warm start, the wiring of rank events, and the component bundle that saves and loads
its own checkpoint state (:class:`OffPolicyComponents`).

A family's builder (:func:`~adarl.runtime.builders.sac.build_sac_components`,
:func:`~adarl.runtime.builders.td3.build_td3_components`) says what is its own, as an :class:`OffPolicyParts`
(networks and loss, optimisers, update step, the parameters the divergence guard checks), and this module builds
the rest in one order, so that a rank event, a warm start, a checkpoint or a resume means the same in every
off-policy loop, and a new family is its parts and nothing else.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler

from adarl.core.acceptance import ProjectionAcceptance, RecentTransitions
from adarl.core.adapter import RankAdapter, resize_to_ranks
from adarl.core.lr_schedule import make_lr_scheduler
from adarl.core.rank import RankRule, registered_rule
from adarl.core.restarts import ScheduledRestarts
from adarl.core.warmstart import ReplayWarmStart
from adarl.errors import AdaRLValueError
from adarl.fast.collector import LeanCollector, wants_lean
from adarl.runtime.builders.common import (
    RunComponents,
    apply_num_threads,
    check_device,
    make_envs,
    train_env_factory,
)
from adarl.runtime.families import check_builder
from adarl.runtime.rank_events import RankEventEffects
from adarl.runtime.state import seed_everything
from adarl.runtime.update import UpdateStep

__all__ = [
    "OffPolicyComponents",
    "OffPolicyParts",
    "build_off_policy_components",
    "update_after",
    "planned_updates",
    "event_threads",
    "make_rank_rule",
    "make_lr_schedulers",
    "make_replay_buffer",
    "make_collector",
    "make_rank_control",
    "wire_rank_events",
]


@dataclass
class OffPolicyComponents(RunComponents):
    """Everything an off-policy recipe builds, wired together (no training has happened yet), and its checkpoint
    state.

    ``update`` is the optimisation step (:class:`~adarl.runtime.update.UpdateStep`); ``sampling_generator`` draws
    the replay indices (checkpointed for exact resume); ``rank_events`` the side effects of rank events, registered
    on ``adapter`` (:class:`~adarl.runtime.rank_events.RankEventEffects`). In a checkpoint (:meth:`state_dict`): the
    loss (its networks and targets), the adapter and the warm start; the replay buffer is saved beside it. A family
    says which parameters the divergence guard checks (:meth:`guarded_parameters`)."""

    recipe: object
    env: object
    eval_env: object
    modules: object
    optimizers: dict[str, torch.optim.Optimizer]
    schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler]
    replay_buffer: TensorDictReplayBuffer
    collector: Collector | LeanCollector
    update: UpdateStep
    adapter: RankAdapter | ScheduledRestarts | None
    warm_start: ReplayWarmStart | None
    total_updates: int
    sampling_generator: torch.Generator
    rank_events: RankEventEffects | None = None

    def _own_state(self) -> dict:
        return {
            "loss": self.modules.loss.state_dict(),
            "adapter": self.adapter.state_dict() if self.adapter is not None else None,
            "warm_start": self.warm_start.state_dict() if self.warm_start is not None else None,
        }

    def _load_networks(self, state: dict) -> None:
        if state.get("adapter") is not None and isinstance(self.adapter, RankAdapter):  # its ranks, then its tensors
            resize_to_ranks(self.modules.loss, state["adapter"], optimizers=list(self.optimizers.values()))
        self.modules.loss.load_state_dict(state["loss"])

    def _load_own_state(self, state: dict) -> None:
        if self.adapter is not None and state.get("adapter") is not None:
            self.adapter.load_state_dict(state["adapter"])
        if self.warm_start is not None and state.get("warm_start") is not None:
            self.warm_start.load_state_dict(state["warm_start"])


def update_after(recipe) -> int:
    """Frames collected before the first optimisation step (``algorithm.update_after``, else the random phase)."""
    a = recipe.algorithm.update_after
    return recipe.collector.init_random_frames if a is None else a


def planned_updates(recipe) -> int:
    """Optimisation steps the recipe's budget allows (frames after the first update times the UTD ratio)."""
    c = recipe.collector
    return max(1, int((c.total_frames - min(update_after(recipe), c.total_frames)) * recipe.algorithm.utd_ratio))


def event_threads(setting, environ=None) -> int | None:
    """``rank.num_threads`` as a thread count: ``'auto'`` = ``OMP_NUM_THREADS`` when set (a launcher's share of the
    machine: 1 for ``adarl experiment -j N > 1``), else every core this process may use; None keeps the run's own.

    >>> event_threads(3), event_threads(None), event_threads("auto", {"OMP_NUM_THREADS": "1"})
    (3, None, 1)
    """
    if setting != "auto":
        return setting
    environ = os.environ if environ is None else environ
    share = environ.get("OMP_NUM_THREADS", "")
    if share.strip().isdigit() and int(share) > 0:
        return int(share)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def make_rank_rule(rank) -> RankRule:
    """The rule of a recipe's ``rank`` section, built one way for every registered rule (adarl's own and a plugin's,
    one table: :data:`adarl.plugins.RANK_RULES`, checked by :func:`~adarl.core.rank.registered_rule`):
    ``rule_class(**arguments)``, the arguments being adarl's own rules' keys (``rank.beta``, ``rank.target_rank``,
    ``rank.lam``) or a plugin rule's ``rank.rule_options`` (:meth:`adarl.plugins.RankRuleSpec.arguments`). A rule
    whose class sets ``needs_fit = True`` gets ``fit(rank)`` from the adapter (on replay states), as ``policy_fit``
    does."""
    cls, spec = registered_rule(rank.rule, spec=True)
    kwargs = spec.arguments(rank)
    try:
        return cls(**kwargs)
    except TypeError as err:
        provider = spec.provider or ("adarl" if spec.builtin else "a register_rank_rule call")
        source = f"its rank keys {kwargs}" if spec.builtin else f"rank.rule_options {rank.rule_options}"
        raise AdaRLValueError(
            f"rank rule {spec.name!r} ({spec.rule_path}, from {provider}) cannot be built from {source}: {err}"
        ) from None


def make_lr_schedulers(recipe, optimizers: dict, total_updates: int, names=("actor", "critic")) -> dict:
    """The warm-up + cosine schedule of ``recipe.lr_schedule`` on each named optimiser (restarted at rank events)."""
    s = recipe.lr_schedule
    return {
        name: make_lr_scheduler(
            optimizers[name],
            warmup_steps=s.warmup_steps,
            total_steps=total_updates if s.cosine else None,
            min_factor=s.min_factor,
        )
        for name in names
    }


def make_replay_buffer(recipe, generator: torch.Generator, scratch_dir=None) -> TensorDictReplayBuffer:
    """The recipe's replay buffer (``replay.size``, ``replay.storage``), sampling ``algorithm.batch_size`` uniformly
    with ``generator`` (checkpointed: exact resume). ``scratch_dir`` holds a memmap storage."""
    return TensorDictReplayBuffer(
        storage=(
            LazyMemmapStorage(recipe.replay.size, scratch_dir=scratch_dir, device=recipe.device)
            if recipe.replay.storage == "memmap"
            else LazyTensorStorage(recipe.replay.size, device=recipe.device)
        ),
        sampler=RandomSampler(),
        batch_size=recipe.algorithm.batch_size,
        generator=generator,
    )


def make_collector(recipe, env, policy, init_random_frames: int | None = None) -> Collector | LeanCollector:
    """The recipe's collector running ``policy`` (the object itself: rank events change it in place): adarl's
    :class:`~adarl.fast.collector.LeanCollector` where ``collector.lean`` asks for it and it applies (one env, a
    TanhNormal actor), else TorchRL's ``Collector``. ``init_random_frames``: None = ``collector.init_random_frames``."""
    c = recipe.collector
    init_random = c.init_random_frames if init_random_frames is None else init_random_frames
    lean = wants_lean(c.lean, env, policy)
    if c.overlap and not lean:
        raise AdaRLValueError(
            f"collector.overlap: {c.overlap!r} needs the lean collector (one env, a TanhNormal "
            "actor, collector.lean: 'auto' or true); allowed otherwise: collector.overlap: false"
        )
    if lean:
        return LeanCollector(
            env,
            policy,
            frames_per_batch=c.frames_per_batch,
            init_random_frames=init_random,
            overlap=c.overlap,
            noise_seed=recipe.seed + 2,
            env_factory=train_env_factory(recipe) if c.overlap == "process" else None,
        )
    return Collector(  # (no recurrent state: the env is left as it is, without TorchRL 0.14's FutureWarning)
        env,
        policy,
        frames_per_batch=c.frames_per_batch,
        total_frames=-1,
        init_random_frames=init_random,
        device=recipe.device,
        auto_register_policy_transforms=False,
    )


def _rank_adapter(recipe, loss, optimizers, schedulers, replay_buffer) -> RankAdapter:
    """The rank adapter of ``recipe.rank``: the rule proposes, the acceptance step decides (Algorithm 1)."""
    r = recipe.rank
    rule = make_rank_rule(r)
    a = r.accept
    # 'fixed' is an instruction (the fixed-rank projection), not a candidate: nothing to accept or refuse
    acceptance = (
        ProjectionAcceptance(a.actor_tol, a.critic_tol, search=a.search)
        if a.mode == "projection" and r.rule != "fixed"
        else None
    )
    return RankAdapter(
        loss,
        list(optimizers.values()),
        rule,
        interval=r.interval,
        scope=r.scope,
        min_rank=r.min_rank,
        target_mode=r.target_mode,
        lr_schedulers=list(schedulers.values()),
        # the acceptance step (and, with 'always', the recorded error) compares outputs on recent transitions
        fit_data=RecentTransitions(replay_buffer, a.samples),
        num_threads=event_threads(r.num_threads),
        acceptance=acceptance,
    )


def make_rank_control(
    recipe, loss, optimizers: dict, schedulers: dict, replay_buffer, collector
) -> tuple[RankAdapter | ScheduledRestarts | None, ReplayWarmStart | None]:
    """``(adapter, warm_start)`` of ``recipe.rank`` and ``recipe.replay.warm_start`` (both None without rank control):
    the :class:`~adarl.core.adapter.RankAdapter` on ``loss`` (or, with ``rank.truncate: false``, the events' LR
    restarts alone), and the warm start refilling ``replay_buffer`` through ``collector``'s own policy."""
    if not recipe.rank.enabled:
        return None, None
    warm_start = None
    w = recipe.replay.warm_start
    if w.mode == "reset" or (w.mode != "keep" and w.frames > 0):
        # LeanCollector.rollout() collects with the loss's own actor, as TorchRL's Collector.rollout() does
        warm_start = ReplayWarmStart(replay_buffer, collector, frames=w.frames, mode=w.mode)
    if recipe.rank.truncate:
        adapter = _rank_adapter(recipe, loss, optimizers, schedulers, replay_buffer)
    else:  # the events' restarts without their truncations (the sac_restarts control)
        adapter = ScheduledRestarts(recipe.rank.interval, list(schedulers.values()), loss_module=loss)
    return adapter, warm_start


def wire_rank_events(adapter, update: UpdateStep, collector, warm_start, parameters: dict) -> RankEventEffects | None:
    """What a rank event sets off (:class:`~adarl.runtime.rank_events.RankEventEffects`), registered on ``adapter``
    (None without one); ``parameters``: the trained tensors by name, whose low-rank factors are checked alive."""
    if adapter is None:
        return None
    factors = {k: v for k, v in parameters.items() if k.endswith((".w1", ".w2"))}
    effects = RankEventEffects(update, collector, warm_start, factors)
    effects.register(adapter)
    return effects


class OffPolicyParts:
    """What one off-policy family builds itself; :func:`build_off_policy_components` builds the rest around it.

    A family's builder makes one (a new instance per build: a part may keep what a later one needs, as SAC's
    optimisers keep whether the update is fused) and overrides:

    * :meth:`modules` - networks, loss and target updater (an object with ``actor`` and ``loss``);
    * :meth:`optimizers` - ``{"actor": ..., "critic": ..., ...}`` (schedules are made for ``actor`` and ``critic``);
    * :meth:`update` - the update step (:class:`~adarl.runtime.update.UpdateStep`);
    * :meth:`parameters` - the trained tensors by readable name (the divergence guard's, the factors' check);
    * :meth:`policy` - what the collector runs (default: ``modules.actor``).

    ``components``: the :class:`OffPolicyComponents` subclass returned."""

    components: type[OffPolicyComponents] = OffPolicyComponents

    def modules(self, recipe, env):
        raise NotImplementedError

    def optimizers(self, recipe, modules) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def update(self, recipe, modules, optimizers, schedulers, replay_buffer, generator) -> UpdateStep:
        raise NotImplementedError

    def parameters(self, recipe, modules) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def policy(self, modules):
        return modules.actor


def build_off_policy_components(
    recipe,
    builder: Callable,
    parts: OffPolicyParts,
    *,
    init_random_frames: int | None = None,
    scratch_dir: str | os.PathLike | None = None,
) -> OffPolicyComponents:
    """The skeleton of every off-policy builder: refuse a recipe of another loop (naming its builder; ``builder``:
    the public builder calling, :func:`adarl.runtime.families.check_builder`), seed, envs, then the family's
    ``parts`` and everything shared, in one order: modules, optimisers, LR schedules, replay buffer, collector, rank
    adapter and warm start, update step, and what a rank event sets off (registered on the adapter: a loop of your
    own gets the same effects as the trainer). ``scratch_dir`` holds a memmap replay storage;
    ``init_random_frames``: None = ``collector.init_random_frames``."""
    check_builder(recipe, builder)
    check_device(recipe.device)
    apply_num_threads(recipe)
    seed_everything(recipe.seed)
    env, eval_env = make_envs(recipe)
    modules = parts.modules(recipe, env)
    optimizers = parts.optimizers(recipe, modules)
    total_updates = planned_updates(recipe)
    schedulers = make_lr_schedulers(recipe, optimizers, total_updates)
    generator = torch.Generator().manual_seed(recipe.seed + 1)
    replay_buffer = make_replay_buffer(recipe, generator, scratch_dir)
    collector = make_collector(recipe, env, parts.policy(modules), init_random_frames)
    adapter, warm_start = make_rank_control(recipe, modules.loss, optimizers, schedulers, replay_buffer, collector)
    update = parts.update(recipe, modules, optimizers, schedulers, replay_buffer, generator)
    effects = wire_rank_events(adapter, update, collector, warm_start, parts.parameters(recipe, modules))
    return parts.components(
        recipe,
        env,
        eval_env,
        modules,
        optimizers,
        schedulers,
        replay_buffer,
        collector,
        update,
        adapter,
        warm_start,
        total_updates,
        generator,
        effects,
    )
