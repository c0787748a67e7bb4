"""Where a SAC recipe becomes objects: actor, critic and ``SACLoss`` (stock TorchRL pieces with
:class:`~adarl.core.lowrank.LowRankLinear` layers), then every component of a run wired together
(:func:`build_sac_components`, :class:`SACComponents`): envs, optimisers, LR schedules, replay buffer, collector, the
update step, the rank adapter with its acceptance step, the warm start, and what a rank event sets off.
``build_components`` and ``Components`` are aliases of the two, the names they had before the PPO loop had its own.

Each network builder takes plain arguments (not the recipe) so that users composing in Python can call them
directly; :func:`make_sac_modules` and :func:`build_sac_components` are the recipe-facing ones. The baselines plug in
through :mod:`adarl.baselines.registry` (network variants, init schemes, loss terms); the speed engine
(:mod:`adarl.fast`) replaces the collector and the update step where it applies (``collector.lean``,
``algorithm.fused``).

>>> from adarl import build_sac_components, load_recipe
>>> recipe = load_recipe("quickstart", ["collector.total_frames=500", "collector.init_random_frames=100",
...                                     "collector.frames_per_batch=100", "replay.size=500",
...                                     "replay.warm_start.frames=100"])
>>> c = build_sac_components(recipe)
>>> type(c.update).__name__, type(c.collector).__name__, c.adapter.named_ranks["actor.layer0"]
('FusedStep', 'LeanCollector', 11)
>>> c.close()
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.envs import EnvBase
from torchrl.modules import OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate, ValueEstimators

from adarl import plugins
from adarl.baselines import registry
from adarl.core.acceptance import ProjectionAcceptance, RecentTransitions
from adarl.core.adapter import RankAdapter, resize_to_ranks
from adarl.core.ensemble import reinit_low_rank_ensemble
from adarl.core.lr_schedule import make_lr_scheduler
from adarl.core.rank import RankRule
from adarl.core.restarts import ScheduledRestarts
from adarl.core.warmstart import ReplayWarmStart
from adarl.errors import AdaRLValueError, AdaRLWarning
from adarl.fast.adam import make_adam
from adarl.fast.collector import LeanCollector, wants_lean
from adarl.fast.sac import FusedSACUpdate, fused_fallback_reason, wants_fused
from adarl.runtime.builders.common import (
    RunComponents,
    action_spec,
    apply_num_threads,
    check_device,
    is_discrete,
    make_envs,
    make_mlp,
    train_env_factory,
)
from adarl.runtime.families import check_family
from adarl.runtime.rank_events import RankEventEffects
from adarl.runtime.state import seed_everything
from adarl.runtime.update import FusedStep, LossStep, UpdateStep

__all__ = [
    "make_sac_actor",
    "make_sac_critic",
    "make_sac_loss",
    "reinit_low_rank_ensemble",
    "SACModules",
    "make_recipe_actor",
    "make_sac_modules",
    "SACComponents",
    "build_sac_components",
    "Components",
    "build_components",
    "sac_parameters",
    "FusedFallbackWarning",
    "update_after",
    "planned_updates",
    "make_rank_rule",
]


def make_sac_actor(env: EnvBase, obs_key="observation", **mlp_kwargs) -> ProbabilisticActor:
    """SAC's stochastic policy: TanhNormal for boxes, OneHotCategorical for discrete action specs."""
    obs_dim = env.observation_spec[obs_key].shape[-1]
    spec = action_spec(env)
    if is_discrete(spec):
        n = spec.space.n
        net = make_mlp(obs_dim, n, **mlp_kwargs)
        module = TensorDictModule(net, in_keys=[obs_key], out_keys=["logits"])
        return ProbabilisticActor(
            module, in_keys=["logits"], spec=spec, distribution_class=OneHotCategorical, return_log_prob=False
        )
    act_dim = spec.shape[-1]
    net = make_mlp(obs_dim, 2 * act_dim, **mlp_kwargs)
    module = TensorDictModule(nn.Sequential(net, NormalParamExtractor()), in_keys=[obs_key], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=False,
    )


def make_sac_critic(env: EnvBase, obs_key="observation", **mlp_kwargs) -> ValueOperator:
    """Q(s, a) for boxes (input ``[s, a]``), or Q(s, .) over all actions for discrete specs."""
    obs_dim = env.observation_spec[obs_key].shape[-1]
    spec = action_spec(env)
    if is_discrete(spec):
        net = make_mlp(obs_dim, spec.space.n, **mlp_kwargs)
        return ValueOperator(net, in_keys=[obs_key], out_keys=["action_value"])
    net = make_mlp(obs_dim + spec.shape[-1], 1, **mlp_kwargs)
    return ValueOperator(net, in_keys=[obs_key, "action"])


def make_sac_loss(
    actor: ProbabilisticActor,
    critic: ValueOperator,
    env: EnvBase,
    *,
    gamma: float = 0.99,
    num_qvalue_nets: int = 2,
    loss_function: str = "l2",
    init_alpha: float = 1.0,
    fixed_alpha: bool = False,
    target_entropy: float | str = "auto",
    loss_class: type[SACLoss] = SACLoss,
    loss_kwargs: dict | None = None,
) -> SACLoss | DiscreteSACLoss:
    """TorchRL's ``SACLoss`` (or ``DiscreteSACLoss``) with the TD(0) estimator, as TorchRL's reference SAC.

    ``loss_class``: a registered algorithm's loss (:mod:`adarl.plugins`), built with ``SACLoss``'s keyword
    arguments and ``loss_kwargs`` (its ``algorithm.options``)."""
    spec = action_spec(env)
    if loss_class is not SACLoss and is_discrete(spec):
        raise AdaRLValueError(
            f"{loss_class.__name__} is built like SACLoss (continuous actions); this env's actions are discrete "
            "(allowed for discrete actions: algorithm.name: 'sac', which uses DiscreteSACLoss)"
        )
    if is_discrete(spec):
        loss = DiscreteSACLoss(
            actor_network=actor,
            qvalue_network=critic,
            action_space=spec,
            num_actions=spec.space.n,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=init_alpha,
            fixed_alpha=fixed_alpha,
            target_entropy=target_entropy,
        )
    else:
        loss = loss_class(
            actor_network=actor,
            qvalue_network=critic,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=init_alpha,
            fixed_alpha=fixed_alpha,
            target_entropy=target_entropy,
            action_spec=spec,
            **(loss_kwargs or {}),
        )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    reinit_low_rank_ensemble(loss)
    return loss


@dataclass
class SACModules:
    """The networks and loss of one SAC agent, with the policy the collector and evaluator run."""

    actor: ProbabilisticActor
    critic: ValueOperator
    loss: SACLoss | DiscreteSACLoss
    target_updater: SoftUpdate


def make_recipe_actor(recipe, env: EnvBase) -> ProbabilisticActor:
    """The SAC actor of a recipe's ``network.actor`` section, for ``env``'s specs (any object with
    ``observation_spec`` and ``action_spec``: :func:`adarl.load_policy` passes the specs a checkpoint saved)."""
    a = recipe.network.actor
    spec = action_spec(env)
    action_dim = spec.space.n if is_discrete(spec) else spec.shape[-1]
    return make_sac_actor(
        env,
        num_cells=a.num_cells,
        activation=a.activation,
        low_rank_layers=a.low_rank_layers,
        rank=a.rank,
        device=torch.device(recipe.device),
        **registry.network_kwargs(a, recipe.algorithm, action_dim),
    )


def make_sac_modules(recipe, env: EnvBase) -> SACModules:
    """Build actor, critic, loss and target updater from a recipe's ``network`` and ``algorithm`` sections."""
    device = torch.device(recipe.device)
    a, c = recipe.network.actor, recipe.network.critic
    spec = action_spec(env)
    action_dim = spec.space.n if is_discrete(spec) else spec.shape[-1]
    alg = recipe.algorithm
    actor = make_recipe_actor(recipe, env)
    critic = make_sac_critic(
        env,
        num_cells=c.num_cells,
        activation=c.activation,
        low_rank_layers=c.low_rank_layers,
        rank=c.rank,
        device=device,
        **registry.network_kwargs(c, alg, action_dim),
    )
    loss = make_sac_loss(
        actor,
        critic,
        env,
        gamma=alg.gamma,
        num_qvalue_nets=alg.num_qvalue_nets,
        loss_function=alg.loss_function,
        init_alpha=alg.init_alpha,
        fixed_alpha=alg.fixed_alpha,
        target_entropy=alg.target_entropy,
        loss_class=plugins.algorithm(alg.name).loss_class(),
        loss_kwargs=dict(alg.options),
    )
    # after the loss exists: SACLoss resamples the stacked critics, so each member is drawn in the loss's params
    for network, mlp in (("actor_network", a), ("qvalue_network", c)):
        init = registry.init_scheme(mlp.init.scheme)
        if init is not None:
            init.loss(loss, network, gain=mlp.init.gain, head_gain=mlp.init.head_gain)
    updater = SoftUpdate(loss, tau=alg.tau)
    return SACModules(actor=actor, critic=critic, loss=loss, target_updater=updater)


@dataclass
class SACComponents(RunComponents):
    """Everything a SAC recipe builds, wired together (no training has happened yet), and its checkpoint state.

    ``update`` is the optimisation step (:class:`~adarl.runtime.update.UpdateStep`: TorchRL's ``SACLoss`` step or
    the fused one); ``sampling_generator`` draws the replay indices (checkpointed for exact resume);
    ``rank_events`` the side effects of rank events, registered on ``adapter``
    (:class:`~adarl.runtime.rank_events.RankEventEffects`). In a checkpoint (:meth:`state_dict`): the loss (its
    networks and targets), the adapter and the warm start; the replay buffer is saved beside it."""

    recipe: object
    env: object
    eval_env: object
    modules: SACModules
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

    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        return sac_parameters(self.modules.loss, self.recipe.algorithm.fixed_alpha)

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


#: the name :class:`SACComponents` had before the PPO loop had its own (kept: an alias)
Components = SACComponents


class FusedFallbackWarning(AdaRLWarning):
    """A registered algorithm's ``SACLoss`` runs TorchRL's (slower) path instead of the fused update, and why."""


def sac_parameters(loss, fixed_alpha: bool = False) -> dict[str, torch.Tensor]:
    """Every tensor a ``SACLoss`` trains, by readable name (``actor.module.0.w1``, ``critic.module.2.bias``,
    ``log_alpha`` unless ``fixed_alpha``): what the divergence guard checks."""
    named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
    named.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items()})
    if not fixed_alpha:
        named["log_alpha"] = loss.log_alpha
    return named


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
    """The rule of a recipe's ``rank`` section, built one way for every registered rule (adarl's own and a plugin's):
    ``rule_class()(**arguments)``, the arguments being adarl's own rules' keys (``rank.beta``, ``rank.target_rank``,
    ``rank.lam``) or a plugin rule's ``rank.rule_options`` (:meth:`adarl.plugins.RankRuleSpec.arguments`). A rule
    whose class sets ``needs_fit = True`` gets ``fit(rank)`` from the adapter (on replay states), as ``policy_fit``
    does."""
    spec = plugins.rank_rule(rank.rule)
    cls = spec.rule_class()
    provider = spec.provider or ("adarl" if spec.builtin else "a register_rank_rule call")
    where = f"rank rule {spec.name!r} ({spec.rule_path}, from {provider})"
    if not (isinstance(cls, type) and issubclass(cls, RankRule)):
        raise AdaRLValueError(f"{where} is not an adarl.core.rank.RankRule subclass (got {cls!r})")
    kwargs = spec.arguments(rank)
    try:
        return cls(**kwargs)
    except TypeError as err:
        source = f"its rank keys {kwargs}" if spec.builtin else f"rank.rule_options {rank.rule_options}"
        raise AdaRLValueError(f"{where} cannot be built from {source}: {err}") from None


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


def _update_step(
    recipe, modules: SACModules, optimizers, schedulers, replay_buffer, generator, *, fused: bool, terms: dict
) -> UpdateStep:
    """The fused step where asked for and possible, else TorchRL's (``algorithm.fused``, ``algorithm.backward``)."""
    alg = recipe.algorithm
    if fused:
        try:
            update = FusedSACUpdate(
                modules.loss,
                list(optimizers.values()),
                tau=alg.tau,
                schedulers=list(schedulers.values()),
                max_grad_norm=alg.max_grad_norm,
                compile=alg.compile,
                backward=alg.backward,
                terms=terms,
            )
        except AdaRLValueError:
            if alg.fused is True or alg.backward == "manual":  # asked for explicitly: say why not
                raise
            # 'auto' with layers the fused step does not know (e.g. the sparsification layer), or a loss term that
            # reads the batch: TorchRL's path.
        else:
            # the same indices rb.sample() would draw, gathered straight into the update's five tensors
            return FusedStep(update, replay_buffer, generator)
    return LossStep(
        modules.loss,
        list(optimizers.values()),
        replay_buffer=replay_buffer,
        target_updater=modules.target_updater,
        schedulers=list(schedulers.values()),
        max_grad_norm=alg.max_grad_norm,
        terms=terms,
    )


def build_sac_components(
    recipe, *, init_random_frames: int | None = None, scratch_dir: str | os.PathLike | None = None
) -> SACComponents:
    """Build env, networks, SAC loss, optimisers, LR schedules, buffer, collector, update step, rank adapter and
    warm start, and wire what a rank event sets off (:class:`~adarl.runtime.rank_events.RankEventEffects`,
    registered on the adapter: a loop of your own gets the same effects as the recipe's trainer).

    With ``algorithm.fused`` the update step is a :class:`~adarl.runtime.update.FusedStep` (same parameters, losses
    and optimisers as the plain path). ``scratch_dir`` holds a memmap replay storage. A recipe on another loop
    (RNAC's PPO) is refused, naming its builder (:func:`adarl.runtime.families.check_family`)."""
    check_family(recipe, "sac")
    check_device(recipe.device)
    apply_num_threads(recipe)
    seed_everything(recipe.seed)
    env, eval_env = make_envs(recipe)
    modules = make_sac_modules(recipe, env)
    loss = modules.loss
    alg = recipe.algorithm

    actor_params = list(loss.actor_network_params.flatten_keys().values())
    critic_params = list(loss.qvalue_network_params.flatten_keys().values())
    terms = registry.loss_terms(loss, alg)
    fused = wants_fused(alg.fused, loss)
    reason = fused_fallback_reason(loss)
    if alg.fused == "auto" and reason is not None and isinstance(loss, SACLoss):
        # a SACLoss of a plugin the fused update cannot compute: say so, once, rather than slow down in silence
        warnings.warn(
            f"algorithm {alg.name!r} runs TorchRL's SACLoss path, not the fused update: {reason}; it costs about "
            "3x the time per update (docs/performance.md)",
            FusedFallbackWarning,
            stacklevel=2,
        )
    optimizers = {
        "actor": make_adam(actor_params, alg.lr, fused=fused),
        "critic": make_adam(critic_params, alg.lr, fused=fused),
    }
    if not alg.fixed_alpha:
        optimizers["alpha"] = make_adam([loss.log_alpha], alg.alpha_lr, fused=fused)
    total_updates = planned_updates(recipe)
    s = recipe.lr_schedule
    schedulers = {
        name: make_lr_scheduler(
            optimizers[name],
            warmup_steps=s.warmup_steps,
            total_steps=total_updates if s.cosine else None,
            min_factor=s.min_factor,
        )
        for name in ("actor", "critic")
    }

    generator = torch.Generator().manual_seed(recipe.seed + 1)
    replay_buffer = TensorDictReplayBuffer(
        storage=(
            LazyMemmapStorage(recipe.replay.size, scratch_dir=scratch_dir, device=recipe.device)
            if recipe.replay.storage == "memmap"
            else LazyTensorStorage(recipe.replay.size, device=recipe.device)
        ),
        sampler=RandomSampler(),
        batch_size=alg.batch_size,
        generator=generator,
    )
    c = recipe.collector
    init_random = c.init_random_frames if init_random_frames is None else init_random_frames
    lean = wants_lean(c.lean, env, modules.actor)
    if c.overlap and not lean:
        raise AdaRLValueError(
            f"collector.overlap: {c.overlap!r} needs the lean collector (one env, a TanhNormal "
            "actor, collector.lean: 'auto' or true); allowed otherwise: collector.overlap: false"
        )
    if lean:
        collector = LeanCollector(
            env,
            modules.actor,
            frames_per_batch=c.frames_per_batch,
            init_random_frames=init_random,
            overlap=c.overlap,
            noise_seed=recipe.seed + 2,
            env_factory=train_env_factory(recipe) if c.overlap == "process" else None,
        )
    else:
        collector = Collector(
            env,
            modules.actor,
            frames_per_batch=c.frames_per_batch,
            total_frames=-1,
            init_random_frames=init_random,
            device=recipe.device,
        )

    adapter = warm_start = None
    if recipe.rank.enabled:
        w = recipe.replay.warm_start
        if w.mode == "reset" or (w.mode != "keep" and w.frames > 0):
            # LeanCollector.rollout() collects with the loss's own actor, as TorchRL's Collector.rollout() does
            warm_start = ReplayWarmStart(replay_buffer, collector, frames=w.frames, mode=w.mode)
        if recipe.rank.truncate:
            adapter = _rank_adapter(recipe, loss, optimizers, schedulers, replay_buffer)
        else:  # the events' restarts without their truncations (the sac_restarts control)
            adapter = ScheduledRestarts(recipe.rank.interval, list(schedulers.values()))
    update = _update_step(recipe, modules, optimizers, schedulers, replay_buffer, generator, fused=fused, terms=terms)
    effects = None
    if adapter is not None:
        factors = {k: v for k, v in sac_parameters(loss, alg.fixed_alpha).items() if k.endswith((".w1", ".w2"))}
        effects = RankEventEffects(update, collector, warm_start, factors)
        effects.register(adapter)
    return SACComponents(
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


#: the name :func:`build_sac_components` had before the PPO loop had its own (kept: an alias)
build_components = build_sac_components
