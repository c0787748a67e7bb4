"""Where a recipe on the ``td3`` loop becomes objects: TorchRL's TD3 (and DDPG) with
:class:`~adarl.core.lowrank.LowRankLinear` layers, and every component of a run wired together
(:func:`build_td3_components`, :class:`TD3Components`).

The pieces are TorchRL's TD3 example's: a deterministic actor (an MLP, then ``TanhModule`` into the action box), a
Q(s, a) critic (the SAC critic, :func:`~adarl.runtime.builders.common.make_sac_critic`), ``TD3Loss`` (target policy
smoothing: ``algorithm.td3.policy_noise``, ``noise_clip``) or ``DDPGLoss`` (one critic), exploration by
``AdditiveGaussianModule`` on the actor's action (``algorithm.td3.exploration_noise``), and delayed actor and target
updates (``algorithm.td3.policy_update_delay``; :class:`~adarl.runtime.update.DelayedActorStep`): :class:`TD3Parts`.
Everything else is every off-policy family's (:mod:`~adarl.runtime.builders.off_policy`'s skeleton): the replay
buffer, TorchRL's collector, the rank adapter and its acceptance step, the warm start (collecting with the
exploration policy), the rank events' effects and the checkpoint state. adarl's fused SAC update and lean
collector are SAC's alone: this loop runs TorchRL's plain path.

A registered algorithm on ``base="td3"`` is built with ``TD3Loss``'s keyword arguments (a ``DDPGLoss`` subclass:
``DDPGLoss``'s) plus its ``algorithm.options`` (docs/custom-loss.md).

>>> from adarl import load_recipe
>>> recipe = load_recipe("baselines/hopper_td3", ["collector.total_frames=500", "collector.init_random_frames=100",
...                                               "collector.frames_per_batch=100", "replay.size=500",
...                                               "replay.warm_start.frames=100"])
>>> c = build_td3_components(recipe)
>>> type(c.modules.loss).__name__, type(c.update).__name__, type(c.collector).__name__
('TD3Loss', 'DelayedActorStep', 'Collector')
>>> c.close()
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import EnvBase
from torchrl.modules import AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate, TD3Loss, ValueEstimators

from adarl import plugins
from adarl.baselines import registry
from adarl.core.ensemble import reinit_low_rank_ensemble
from adarl.errors import AdaRLValueError
from adarl.fast.adam import make_adam
from adarl.runtime.builders.common import action_spec, is_discrete, make_mlp, make_sac_critic, recipe_mlp_kwargs
from adarl.runtime.builders.off_policy import OffPolicyComponents, OffPolicyParts, build_off_policy_components
from adarl.runtime.update import DelayedActorStep

__all__ = [
    "make_td3_actor",
    "make_exploration_policy",
    "make_td3_loss",
    "make_recipe_td3_actor",
    "TD3Modules",
    "make_td3_modules",
    "td3_parameters",
    "TD3Components",
    "TD3Parts",
    "build_td3_components",
]


def make_td3_actor(env: EnvBase, obs_key="observation", **mlp_kwargs) -> TensorDictSequential:
    """TD3's deterministic policy, as TorchRL's TD3 example builds it: an MLP writing ``param``, then
    ``TanhModule`` squashing it into the action box (``action``). Box actions only."""
    spec = action_spec(env)
    if is_discrete(spec):
        raise AdaRLValueError("the td3 loop (TD3Loss, DDPGLoss) needs a box action space; this env's is discrete")
    obs_dim = env.observation_spec[obs_key].shape[-1]
    net = make_mlp(obs_dim, spec.shape[-1], **mlp_kwargs)
    return TensorDictSequential(
        TensorDictModule(net, in_keys=[obs_key], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )


def make_exploration_policy(actor: TensorDictSequential, env: EnvBase, noise: float) -> TensorDictSequential:
    """The collector's policy: ``actor`` (the object itself: rank events change it in place) followed by TorchRL's
    ``AdditiveGaussianModule`` with a constant std of ``noise`` (the action projected back into the box); under
    ``ExplorationType.DETERMINISTIC`` (evaluation) it adds nothing."""
    spec = action_spec(env)
    noise_module = AdditiveGaussianModule(
        spec=spec, sigma_init=1.0, sigma_end=1.0, mean=0.0, std=noise, device=spec.device
    )
    return TensorDictSequential(actor, noise_module)


def make_td3_loss(
    actor: TensorDictSequential,
    critic: ValueOperator,
    env: EnvBase,
    *,
    gamma: float = 0.99,
    num_qvalue_nets: int = 2,
    loss_function: str = "l2",
    policy_noise: float = 0.2,
    noise_clip: float = 0.5,
    loss_class: type = TD3Loss,
    loss_kwargs: dict | None = None,
) -> TD3Loss | DDPGLoss:
    """TorchRL's ``TD3Loss`` (or a subclass; a ``DDPGLoss`` subclass is built with ``DDPGLoss``'s arguments: one
    critic, no target-policy noise) with the TD(0) estimator, TD3's stacked critics drawn member by member
    (:func:`~adarl.core.ensemble.reinit_low_rank_ensemble`)."""
    if issubclass(loss_class, DDPGLoss):
        loss = loss_class(
            actor_network=actor,
            value_network=critic,
            loss_function=loss_function,
            delay_actor=True,
            delay_value=True,
            **(loss_kwargs or {}),
        )
    elif issubclass(loss_class, TD3Loss):
        loss = loss_class(
            actor_network=actor,
            qvalue_network=critic,
            action_spec=action_spec(env),
            num_qvalue_nets=num_qvalue_nets,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            loss_function=loss_function,
            **(loss_kwargs or {}),
        )
    else:
        raise AdaRLValueError(f"the td3 loop builds TD3Loss or DDPGLoss subclasses, got {loss_class.__name__}")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    if isinstance(loss, TD3Loss):  # DDPGLoss's one critic keeps the module's own parameters (nothing resampled)
        reinit_low_rank_ensemble(loss)
    return loss


@dataclass
class TD3Modules:
    """The networks and loss of one TD3 (or DDPG) agent; ``actor`` is deterministic (evaluation), ``exploration``
    the collector's policy (the actor plus Gaussian noise)."""

    actor: TensorDictSequential
    exploration: TensorDictSequential
    critic: ValueOperator
    loss: TD3Loss | DDPGLoss
    target_updater: SoftUpdate


def make_recipe_td3_actor(recipe, env: EnvBase) -> TensorDictSequential:
    """The TD3 actor of a recipe's ``network.actor`` section for ``env``'s specs (:func:`adarl.load_policy` passes
    the specs a checkpoint saved)."""
    a = recipe.network.actor
    return make_td3_actor(env, **recipe_mlp_kwargs(a, recipe.algorithm, action_spec(env).shape[-1], recipe.device))


def make_td3_modules(recipe, env: EnvBase) -> TD3Modules:
    """Actor, exploration policy, critic, loss and target updater from a recipe's ``network`` and ``algorithm``."""
    c, alg, t = recipe.network.critic, recipe.algorithm, recipe.algorithm.td3
    actor = make_recipe_td3_actor(recipe, env)
    critic = make_sac_critic(env, **recipe_mlp_kwargs(c, alg, action_spec(env).shape[-1], recipe.device))
    spec = plugins.algorithm(alg.name)
    loss = make_td3_loss(
        actor,
        critic,
        env,
        gamma=alg.gamma,
        num_qvalue_nets=alg.num_qvalue_nets,
        loss_function=alg.loss_function,
        policy_noise=t.policy_noise,
        noise_clip=t.noise_clip,
        loss_class=spec.loss_class(),
        loss_kwargs=dict(alg.options) if spec.options_to_loss else {},
    )
    critic_name = "value_network" if isinstance(loss, DDPGLoss) else "qvalue_network"
    for network, mlp in (("actor_network", recipe.network.actor), (critic_name, c)):
        init = registry.init_scheme(mlp.init.scheme)
        if init is not None:
            init.loss(loss, network, gain=mlp.init.gain, head_gain=mlp.init.head_gain)
    exploration = make_exploration_policy(actor, env, t.exploration_noise)
    return TD3Modules(actor, exploration, critic, loss, SoftUpdate(loss, tau=alg.tau))


def td3_parameters(loss: TD3Loss | DDPGLoss) -> dict[str, torch.Tensor]:
    """Every tensor a ``TD3Loss`` / ``DDPGLoss`` trains, by readable name (``actor.module.0.w1``,
    ``critic.module.2.bias``): what the divergence guard checks."""
    critic = loss.value_network_params if isinstance(loss, DDPGLoss) else loss.qvalue_network_params
    named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
    named.update({f"critic.{k}": v for k, v in critic.flatten_keys(".").items()})
    return named


@dataclass
class TD3Components(OffPolicyComponents):
    """Everything a recipe on the ``td3`` loop builds, wired together, and its checkpoint state
    (:class:`~adarl.runtime.builders.off_policy.OffPolicyComponents`'s, as SAC's). ``modules`` is a
    :class:`TD3Modules`; the collector runs ``modules.exploration``, evaluation ``modules.actor``."""

    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        return td3_parameters(self.modules.loss)


class TD3Parts(OffPolicyParts):
    """What the ``td3`` family builds itself: the deterministic actor, its exploration policy (what the collector
    runs), the critic and ``TD3Loss`` / ``DDPGLoss``, plain Adam, and the delayed-actor update step."""

    components = TD3Components

    def modules(self, recipe, env) -> TD3Modules:
        return make_td3_modules(recipe, env)

    def optimizers(self, recipe, modules: TD3Modules) -> dict[str, torch.optim.Optimizer]:
        params, lr = td3_parameters(modules.loss), recipe.algorithm.lr
        return {
            "actor": make_adam([v for k, v in params.items() if k.startswith("actor.")], lr, fused=False),
            "critic": make_adam([v for k, v in params.items() if k.startswith("critic.")], lr, fused=False),
        }

    def update(self, recipe, modules, optimizers, schedulers, replay_buffer, generator) -> DelayedActorStep:
        alg = recipe.algorithm
        return DelayedActorStep(
            modules.loss,
            optimizers,
            replay_buffer=replay_buffer,
            target_updater=modules.target_updater,
            policy_update_delay=alg.td3.policy_update_delay,
            schedulers=list(schedulers.values()),
            max_grad_norm=alg.max_grad_norm,
            terms=registry.loss_terms(modules.loss, alg),
        )

    def parameters(self, recipe, modules) -> dict[str, torch.Tensor]:
        return td3_parameters(modules.loss)

    def policy(self, modules: TD3Modules):
        return modules.exploration


def build_td3_components(
    recipe, *, init_random_frames: int | None = None, scratch_dir: str | os.PathLike | None = None
) -> TD3Components:
    """Build env, networks, the TD3 (or DDPG) loss, optimisers, LR schedules, buffer, collector, the delayed-actor
    update step, rank adapter and warm start, and wire what a rank event sets off, as
    :func:`~adarl.runtime.builders.sac.build_sac_components` does for SAC (one skeleton:
    :func:`~adarl.runtime.builders.off_policy.build_off_policy_components`). A recipe on another loop is refused,
    naming its builder (:func:`adarl.runtime.families.check_builder`)."""
    return build_off_policy_components(
        recipe, build_td3_components, TD3Parts(), init_random_frames=init_random_frames, scratch_dir=scratch_dir
    )
