"""Where a SAC recipe becomes objects: actor, critic and ``SACLoss`` (stock TorchRL pieces with
:class:`~adarl.core.lowrank.LowRankLinear` layers), then every component of a run wired together
(:func:`build_sac_components`, :class:`SACComponents`): envs, optimisers, LR schedules, replay buffer, collector, the
update step, the rank adapter with its acceptance step, the warm start, and what a rank event sets off. What is
SAC's own is :class:`SACParts` (networks and loss, optimisers, the fused or TorchRL update step); the skeleton and the
pieces every off-policy family shares are :mod:`~adarl.runtime.builders.off_policy`'s, the critic
:mod:`~adarl.runtime.builders.common`'s (TD3 shares it).

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
from torchrl.envs import EnvBase
from torchrl.modules import OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate, ValueEstimators

from adarl import plugins
from adarl.baselines import registry
from adarl.core.ensemble import reinit_low_rank_ensemble
from adarl.core.product_polyak import ProductSoftUpdate, factor_keys
from adarl.errors import AdaRLValueError, FusedFallbackWarning
from adarl.fast.adam import make_adam
from adarl.fast.sac import FusedSACUpdate, fused_fallback_reason, wants_fused
from adarl.runtime.builders._crossq_nets import make_crossq_actor
from adarl.runtime.builders.common import action_spec, is_discrete, make_mlp, make_sac_critic, recipe_mlp_kwargs
from adarl.runtime.builders.off_policy import (
    OffPolicyComponents,
    OffPolicyParts,
    build_off_policy_components,
    event_threads,
    make_rank_rule,
    planned_updates,
    update_after,
)
from adarl.runtime.update import FusedStep, LossStep, UpdateStep

__all__ = [
    "make_sac_actor",
    "make_sac_loss",
    "reinit_low_rank_ensemble",
    "SACModules",
    "make_recipe_actor",
    "make_sac_modules",
    "SACComponents",
    "build_sac_components",
    "SACParts",
    "sac_parameters",
    "update_after",
    "planned_updates",
    "make_rank_rule",
    "event_threads",
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


#: the TQC / CrossQ / REDQ skeleton parts, ``{"parts": VariantParts}``: registered by
#: :mod:`~adarl.runtime.builders.sac_variants` (which builds on this module; the ``adarl.runtime.builders`` package
#: imports it, so it is registered before any builder runs)
VARIANT_PARTS: dict[str, type] = {}


def make_recipe_actor(recipe, env: EnvBase) -> ProbabilisticActor:
    """The SAC actor of a recipe's ``network.actor`` section, for ``env``'s specs (any object with
    ``observation_spec`` and ``action_spec``: :func:`adarl.load_policy` passes the specs a checkpoint saved);
    CrossQ's has Batch Renormalization layers (:func:`~adarl.runtime.builders.sac_variants.make_crossq_actor`)."""
    if plugins.sac_variant(recipe.algorithm.name) == "CrossQLoss":
        actor = make_crossq_actor(recipe, env)
        if actor is not None:
            return actor
    a = recipe.network.actor
    spec = action_spec(env)
    action_dim = spec.space.n if is_discrete(spec) else spec.shape[-1]
    return make_sac_actor(env, **recipe_mlp_kwargs(a, recipe.algorithm, action_dim, recipe.device))


def make_sac_modules(recipe, env: EnvBase) -> SACModules:
    """Build actor, critic, loss and target updater from a recipe's ``network`` and ``algorithm`` sections."""
    device = torch.device(recipe.device)
    a, c = recipe.network.actor, recipe.network.critic
    spec = action_spec(env)
    action_dim = spec.space.n if is_discrete(spec) else spec.shape[-1]
    alg = recipe.algorithm
    actor = make_recipe_actor(recipe, env)
    critic = make_sac_critic(env, **recipe_mlp_kwargs(c, alg, action_dim, device))
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
    # algorithm.polyak: 'product' averages the factorised layers' products (adarl.core.product_polyak)
    updater = ProductSoftUpdate(loss, tau=alg.tau) if alg.polyak == "product" else SoftUpdate(loss, tau=alg.tau)
    return SACModules(actor=actor, critic=critic, loss=loss, target_updater=updater)


@dataclass
class SACComponents(OffPolicyComponents):
    """Everything a SAC recipe builds, wired together (no training has happened yet), and its checkpoint state
    (:class:`~adarl.runtime.builders.off_policy.OffPolicyComponents`: the loss, adapter, warm start, optimisers, ...).

    ``update`` is the optimisation step (:class:`~adarl.runtime.update.UpdateStep`: TorchRL's ``SACLoss`` step or
    the fused one); ``modules`` a :class:`SACModules`."""

    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        return sac_parameters(self.modules.loss, self.recipe.algorithm.fixed_alpha)


def sac_parameters(loss, fixed_alpha: bool = False) -> dict[str, torch.Tensor]:
    """Every tensor a ``SACLoss`` trains, by readable name (``actor.module.0.w1``, ``critic.module.2.bias``,
    ``log_alpha`` unless ``fixed_alpha``): what the divergence guard checks."""
    named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
    named.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items()})
    if not fixed_alpha:
        named["log_alpha"] = loss.log_alpha
    return named


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
                polyak=alg.polyak,
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


def _split_factors(params) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """A network's parameters as (the rest, the low-rank factors ``w1``/``w2``), each in the loss's order."""
    flat = dict(params.flatten_keys().items())
    factors = factor_keys(flat)
    return [v for k, v in flat.items() if k not in factors], [v for k, v in flat.items() if k in factors]


class SACParts(OffPolicyParts):
    """What the ``sac`` family builds itself: its networks and ``SACLoss``, Adam optimisers (the low-rank factors in
    a second group at ``lr * algorithm.factor_lr_scale``; alpha's unless fixed), and the update step: the fused one
    where ``algorithm.fused`` asks for it and it applies, else TorchRL's."""

    components = SACComponents

    def modules(self, recipe, env) -> SACModules:
        return make_sac_modules(recipe, env)

    def optimizers(self, recipe, modules: SACModules) -> dict[str, torch.optim.Optimizer]:
        loss, alg = modules.loss, recipe.algorithm
        actor_params, actor_factors = _split_factors(loss.actor_network_params)
        critic_params, critic_factors = _split_factors(loss.qvalue_network_params)
        self.terms = registry.loss_terms(loss, alg)
        self.fused = wants_fused(alg.fused, loss)
        reason = fused_fallback_reason(loss)
        if alg.fused == "auto" and reason is not None and isinstance(loss, SACLoss):
            # a SACLoss of a plugin the fused update cannot compute: say so, once, rather than slow down in silence
            warnings.warn(
                f"algorithm {alg.name!r} runs TorchRL's SACLoss path, not the fused update: {reason}; it costs about "
                "3x the time per update (docs/performance.md)",
                FusedFallbackWarning,
                stacklevel=4,
            )
        fused, scale = self.fused, alg.factor_lr_scale
        optimizers = {
            "actor": make_adam(actor_params, alg.lr, fused=fused, scaled=actor_factors, scale=scale),
            "critic": make_adam(critic_params, alg.lr, fused=fused, scaled=critic_factors, scale=scale),
        }
        if not alg.fixed_alpha:
            optimizers["alpha"] = make_adam([loss.log_alpha], alg.alpha_lr, fused=fused)
        return optimizers

    def update(self, recipe, modules, optimizers, schedulers, replay_buffer, generator) -> UpdateStep:
        return _update_step(
            recipe, modules, optimizers, schedulers, replay_buffer, generator, fused=self.fused, terms=self.terms
        )

    def parameters(self, recipe, modules) -> dict[str, torch.Tensor]:
        return sac_parameters(modules.loss, recipe.algorithm.fixed_alpha)


def build_sac_components(
    recipe, *, init_random_frames: int | None = None, scratch_dir: str | os.PathLike | None = None
) -> SACComponents:
    """Build env, networks, SAC loss, optimisers, LR schedules, buffer, collector, update step, rank adapter and
    warm start, and wire what a rank event sets off (:class:`~adarl.runtime.rank_events.RankEventEffects`,
    registered on the adapter: a loop of your own gets the same effects as the recipe's trainer).

    With ``algorithm.fused`` the update step is a :class:`~adarl.runtime.update.FusedStep` (same parameters, losses
    and optimisers as the plain path). ``scratch_dir`` holds a memmap replay storage. A recipe on another loop
    (RNAC's PPO, TD3) is refused, naming its builder (:func:`adarl.runtime.families.check_builder`). The skeleton:
    :func:`~adarl.runtime.builders.off_policy.build_off_policy_components`. TQC, CrossQ and REDQ
    (``algorithm.name`` ``tqc``, ``crossq``, ``redq``) build their own networks, loss and step
    (:mod:`~adarl.runtime.builders.sac_variants`)."""
    parts = SACParts() if plugins.sac_variant(recipe.algorithm.name) is None else VARIANT_PARTS["parts"]()
    return build_off_policy_components(
        recipe, build_sac_components, parts, init_random_frames=init_random_frames, scratch_dir=scratch_dir
    )
