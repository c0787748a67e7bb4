"""TorchRL's TQC, CrossQ and REDQ losses on the ``sac`` loop: ``algorithm.name: tqc``, ``crossq``, ``redq``.

Each is TorchRL 0.14's own loss (``TQCLoss``, ``CrossQLoss``, ``REDQLoss``) with the SAC family's stochastic actor,
its Q(s, a) critic (TQC's outputs ``num_quantiles`` atoms; CrossQ's has Batch Renormalization layers), and the
authors' hyperparameters as ``algorithm.options`` (:mod:`adarl.plugins`: ``TQCOptions``, ``CrossQOptions``,
``REDQOptions``). Everything else is the ``sac`` family's (:mod:`~adarl.runtime.builders.off_policy`'s skeleton):
envs, replay buffer, collector, the rank adapter with its acceptance step, warm start, rank events, checkpoints.
What differs is :class:`VariantParts`: the networks and loss, Adam (CrossQ's betas), and the update step
(:class:`DelayedPolicyStep`: the actor and alpha every ``policy_delay``-th critic step, CrossQ's and REDQ's
habit; the target critics every step, none for CrossQ). adarl's fused SAC update computes ``SACLoss`` only, so
these run TorchRL's plain path.

Why CrossQ's networks are built here: its critic normalises the current and next (state, action) pairs in one
batch (the point of the method), with ``torchrl.modules.BatchRenorm1d`` after the input and after each hidden
activation (the authors' layout). Between updates the networks stay in eval mode, so the collector, evaluation,
the rank adapter's probes and ``load_policy`` read the running statistics and never update them; the update step
switches them to train mode for the loss and back.

>>> from adarl import load_recipe
>>> from adarl.runtime.builders import build_sac_components
>>> recipe = load_recipe("baselines/hopper_redq", ["collector.total_frames=500", "collector.init_random_frames=100",
...                                                "collector.frames_per_batch=100", "replay.size=500",
...                                                "replay.warm_start.frames=100"])
>>> c = build_sac_components(recipe)
>>> type(c.modules.loss).__name__, type(c.update).__name__, c.modules.loss.num_qvalue_nets
('REDQLoss', 'DelayedPolicyStep', 10)
>>> c.close()
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import CrossQLoss, REDQLoss, SoftUpdate, TQCLoss, ValueEstimators

from adarl import plugins
from adarl.baselines import registry
from adarl.core.ensemble import reinit_low_rank_ensemble
from adarl.core.product_polyak import ProductSoftUpdate
from adarl.errors import AdaRLValueError
from adarl.fast.adam import make_adam
from adarl.runtime.builders._crossq_nets import (
    VARIANTS,
    BatchRenormLayer,
    _Concat,
    _options,
    make_batch_renorm_mlp,
    make_crossq_actor,
    variant_of,
)
from adarl.runtime.builders.common import action_spec, is_discrete, make_mlp, recipe_mlp_kwargs
from adarl.runtime.builders.off_policy import OffPolicyParts
from adarl.runtime.builders.sac import VARIANT_PARTS, SACComponents, make_recipe_actor
from adarl.runtime.guards import NonFiniteGuard
from adarl.runtime.update import (
    SAC_LOSSES,
    UpdateStep,
    delayed_optimisation,
    loss_output,
    require_losses,
    scalar_entries,
)

__all__ = [
    "VARIANTS",
    "variant_of",
    "BatchRenormLayer",
    "make_batch_renorm_mlp",
    "make_crossq_actor",
    "VariantComponents",
    "variant_parameters",
    "VariantModules",
    "make_variant_modules",
    "DelayedPolicyStep",
    "VariantParts",
]


def _critic(recipe, env: EnvBase, variant: str, opts) -> ValueOperator:
    c, spec = recipe.network.critic, action_spec(env)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], spec.shape[-1]
    kwargs = recipe_mlp_kwargs(c, recipe.algorithm, act_dim, recipe.device)
    if variant == "CrossQLoss":
        net = make_batch_renorm_mlp(
            obs_dim + act_dim, 1, momentum=opts.batch_norm_momentum, warmup_steps=opts.renorm_warmup_steps, **kwargs
        )
        return ValueOperator(_Concat(*net), in_keys=["observation", "action"]).eval()
    out = opts.num_quantiles if variant == "TQCLoss" else 1
    return ValueOperator(make_mlp(obs_dim + act_dim, out, **kwargs), in_keys=["observation", "action"])


@dataclass
class VariantModules:
    """The networks and loss of one TQC / CrossQ / REDQ agent (``target_updater``: None for CrossQ, which has no
    target network); ``batch_norm``: the modules the update step switches to train mode (CrossQ's)."""

    actor: ProbabilisticActor
    critic: ValueOperator
    loss: TQCLoss | CrossQLoss | REDQLoss
    target_updater: SoftUpdate | None
    batch_norm: tuple[nn.Module, ...] = ()


def make_variant_modules(recipe, env: EnvBase) -> VariantModules:
    """Actor, critic, the TorchRL loss (TD(0) targets, ``algorithm.gamma``) and its target updater."""
    alg, spec = recipe.algorithm, action_spec(env)
    if is_discrete(spec):
        raise AdaRLValueError(f"algorithm.name {alg.name!r} needs a box action space; this env's is discrete")
    variant = variant_of(recipe)
    opts = _options(recipe, variant)
    aspec = plugins.algorithm(alg.name)
    cls = aspec.loss_class()
    extra = {} if aspec.options is VARIANTS[variant] else dict(alg.options)
    actor, critic = make_recipe_actor(recipe, env), _critic(recipe, env, variant, opts)
    common = dict(
        alpha_init=alg.init_alpha, fixed_alpha=alg.fixed_alpha, target_entropy=alg.target_entropy, action_spec=spec
    )
    if variant == "TQCLoss":
        loss = cls(
            actor,
            critic,
            num_qvalue_nets=opts.num_critics,
            top_quantiles_to_drop_per_net=opts.top_quantiles_to_drop_per_net,
            **common,
            **extra,
        )
    elif variant == "CrossQLoss":
        loss = cls(
            actor, critic, num_qvalue_nets=alg.num_qvalue_nets, loss_function=alg.loss_function, **common, **extra
        )
    else:  # REDQ: the authors' temperature is unbounded (TorchRL's default keeps it in [0.1, 10])
        loss = cls(
            actor,
            critic,
            num_qvalue_nets=opts.ensemble_size,
            sub_sample_len=opts.subset_size,
            loss_function=alg.loss_function,
            min_alpha=0.0,
            max_alpha=float("inf"),
            delay_qvalue=True,
            **common,
            **extra,
        )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=alg.gamma)
    # REDQLoss registers its target-entropy buffer at first use: now, so that a checkpoint loads before any update
    _ = loss.target_entropy
    reinit_low_rank_ensemble(loss)
    for network, mlp in (("actor_network", recipe.network.actor), ("qvalue_network", recipe.network.critic)):
        init = registry.init_scheme(mlp.init.scheme)
        if init is not None:
            init.loss(loss, network, gain=mlp.init.gain, head_gain=mlp.init.head_gain)
    if variant == "CrossQLoss":
        updater, norms = None, (actor, critic)
    else:
        updater = ProductSoftUpdate(loss, tau=alg.tau) if alg.polyak == "product" else SoftUpdate(loss, tau=alg.tau)
        norms = ()
    return VariantModules(actor, critic, loss, updater, norms)


def variant_parameters(loss, fixed_alpha: bool = False) -> dict[str, torch.Tensor]:
    """The trained tensors by readable name (``actor.module.0.w1``, ``critic.module.2.bias``, ``log_alpha``): the
    divergence guard's; CrossQ's running statistics are buffers, not trained, and left out."""
    named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items() if v.requires_grad}
    named.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items() if v.requires_grad})
    if not fixed_alpha:
        named["log_alpha"] = loss.log_alpha
    return named


class DelayedPolicyStep(UpdateStep):
    """One step with TorchRL's pieces: ``loss(rb.sample())``, backward of its ``loss_*`` entries, per-optimiser
    gradient clipping, the critic's optimiser every step, the actor's and alpha's every ``policy_delay``-th step
    (``update + 1`` a multiple of it; their gradients of an off step are dropped), the LR schedules and the target
    critics (``target_updater``; None: CrossQ, no target network) every step. ``batch_norm``: modules switched to
    train mode for the loss and back to eval mode after it. ``policy_delay=1`` is SAC's (and TQC's) step."""

    def __init__(
        self,
        loss: nn.Module,
        optimizers: Mapping[str, torch.optim.Optimizer],
        *,
        replay_buffer: TensorDictReplayBuffer,
        target_updater: SoftUpdate | None,
        policy_delay: int = 1,
        schedulers: Sequence = (),
        max_grad_norm: float | None = None,
        terms: Mapping[str, nn.Module] | None = None,
        batch_norm: Sequence[nn.Module] = (),
    ) -> None:
        self.loss, self.optimizers, self.schedulers = loss, dict(optimizers), list(schedulers)
        self.replay_buffer, self.target_updater = replay_buffer, target_updater
        self.delay, self.max_grad_norm, self.terms = int(policy_delay), max_grad_norm, dict(terms or {})
        self.batch_norm = tuple(batch_norm)

    def updates_policy(self, update: int) -> bool:
        """Whether step ``update`` (0-based) steps the actor and alpha."""
        return (update + 1) % self.delay == 0

    def __call__(self, guard: NonFiniteGuard | None = None, *, update: int = 0) -> dict[str, torch.Tensor]:
        for m in self.batch_norm:
            m.train()
        try:
            td, losses = loss_output(self.loss, self.replay_buffer.sample(), self.terms)
        finally:
            for m in self.batch_norm:
                m.eval()
        require_losses(losses, SAC_LOSSES, self.loss, "SAC")
        policy_too = self.updates_policy(update)
        stepped = [o for name, o in self.optimizers.items() if policy_too or name == "critic"]
        delayed_optimisation(self, losses, stepped, guard, update)
        if self.target_updater is not None:
            self.target_updater.step()
        if guard is not None:
            guard.check_params(update)
        return scalar_entries(td)


def _split_factors(params) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """A network's trained tensors as (the rest, the low-rank factors ``w1``/``w2``); buffers left out."""
    flat = {k: v for k, v in params.flatten_keys().items() if v.requires_grad}
    factors = {k for k in flat if k.rpartition(".")[2] in ("w1", "w2")}
    return [v for k, v in flat.items() if k not in factors], [v for k, v in flat.items() if k in factors]


class VariantParts(OffPolicyParts):
    """What the ``sac`` family builds for TQC, CrossQ and REDQ: their networks and TorchRL loss, Adam for actor,
    critic and alpha (the low-rank factors at ``lr * algorithm.factor_lr_scale``; CrossQ's betas), and
    :class:`DelayedPolicyStep` (CrossQ's and REDQ's ``policy_delay``; 1 for TQC)."""

    components = None  # VariantComponents, set below

    def modules(self, recipe, env) -> VariantModules:
        return make_variant_modules(recipe, env)

    def optimizers(self, recipe, modules: VariantModules) -> dict[str, torch.optim.Optimizer]:
        loss, alg = modules.loss, recipe.algorithm
        scale = alg.factor_lr_scale
        actor_params, actor_factors = _split_factors(loss.actor_network_params)
        critic_params, critic_factors = _split_factors(loss.qvalue_network_params)
        optimizers = {
            "actor": make_adam(actor_params, alg.lr, fused=False, scaled=actor_factors, scale=scale),
            "critic": make_adam(critic_params, alg.lr, fused=False, scaled=critic_factors, scale=scale),
        }
        if not alg.fixed_alpha:
            optimizers["alpha"] = make_adam([loss.log_alpha], alg.alpha_lr, fused=False)
        if variant_of(recipe) == "CrossQLoss":
            opts = _options(recipe, "CrossQLoss")
            for opt in optimizers.values():
                for group in opt.param_groups:
                    group["betas"] = (opts.adam_beta1, opts.adam_beta2)
                opt.defaults["betas"] = (opts.adam_beta1, opts.adam_beta2)
        return optimizers

    def update(self, recipe, modules: VariantModules, optimizers, schedulers, replay_buffer, generator):
        variant = variant_of(recipe)
        delay = 1 if variant == "TQCLoss" else _options(recipe, variant).policy_delay
        return DelayedPolicyStep(
            modules.loss,
            optimizers,
            replay_buffer=replay_buffer,
            target_updater=modules.target_updater,
            policy_delay=delay,
            schedulers=list(schedulers.values()),
            max_grad_norm=recipe.algorithm.max_grad_norm,
            terms=registry.loss_terms(modules.loss, recipe.algorithm),
            batch_norm=modules.batch_norm,
        )

    def parameters(self, recipe, modules: VariantModules) -> dict[str, torch.Tensor]:
        return variant_parameters(modules.loss, recipe.algorithm.fixed_alpha)


@dataclass
class VariantComponents(SACComponents):
    """Everything a TQC / CrossQ / REDQ recipe builds (:class:`~adarl.runtime.builders.sac.SACComponents`'s state);
    ``modules`` is a :class:`VariantModules`."""

    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        return variant_parameters(self.modules.loss, self.recipe.algorithm.fixed_alpha)


VariantParts.components = VariantComponents


VARIANT_PARTS["parts"] = VariantParts  # build_sac_components builds TQC / CrossQ / REDQ with these
