"""Where a PPO recipe (the RNAC baselines, Zhou et al., 2023) becomes objects: actor, state-value critic,
TorchRL's ``ClipPPOLoss`` (or the registered algorithm's loss) and GAE (or the algorithm's ``advantage`` hook:
RNAC-IPM's shifted GAE), then every component of a run wired together (:func:`build_ppo_components`): envs (plus the
algorithm's ``env_transform`` hook: RNAC-DS's double sampling), optimisers, the linear LR decay and the collector.

Defaults follow the original RNAC trainer (tliu1997/RNAC): 64-64 tanh networks with its orthogonal init
(``network.<net>.init`` in the recipes), its Gaussian policy (mean ``tanh`` into the box, state-independent
log-std, samples clipped to the action box: :class:`~adarl.baselines.policy.ClippedNormal`), Adam (eps 1e-5) with
a linear learning-rate decay, running observation normalisation and reward scaling. ``algorithm.ppo.policy:
tanh_gaussian`` gives TorchRL's tanh-squashed Gaussian instead; docs/baselines/rnac.md lists what still differs
from the original. The loop is :class:`~adarl.runtime.trainers.ppo.PPOTrainer`.
"""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass, field

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import Transform
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from adarl import plugins
from adarl.baselines import registry
from adarl.baselines.normalization import RewardScaler, RunningObsNorm
from adarl.baselines.policy import BoxTanh, ClippedNormal
from adarl.baselines.rnac import DoubleSamplingTransform
from adarl.runtime.builders.common import (
    RunComponents,
    action_spec,
    apply_num_threads,
    check_device,
    init_network,
    make_envs,
    make_recipe_mlp,
)
from adarl.runtime.families import check_builder
from adarl.runtime.state import seed_everything

__all__ = [
    "PPOModules",
    "PPOComponents",
    "LinearDecay",
    "make_ppo_modules",
    "make_recipe_ppo_actor",
    "build_ppo_components",
    "simulator_steps_per_frame",
]


@dataclass
class PPOModules:
    """Actor, critic, PPO loss and advantage module of one PPO/RNAC agent (``obs_norms`` sit inside actor and
    critic)."""

    actor: ProbabilisticActor
    critic: ValueOperator
    loss: ClipPPOLoss
    advantage: GAE
    obs_norms: list[RunningObsNorm]


@dataclass
class PPOComponents(RunComponents):
    """Everything a PPO recipe builds, wired together (no training has happened yet), and its checkpoint state.
    ``terms``: the loss terms the recipe switches on (:mod:`adarl.baselines.registry`: Parseval);
    ``sampling_generator`` draws the minibatches. In a checkpoint (:meth:`state_dict`): actor and critic (their
    observation statistics included), the reward scaler, RNAC-DS's generator and counters."""

    recipe: object
    env: object
    eval_env: object
    modules: PPOModules
    optimizers: dict[str, torch.optim.Optimizer]
    schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler]
    collector: Collector
    reward_scaler: RewardScaler | None
    env_transform: Transform | None
    total_iterations: int
    sampling_generator: torch.Generator
    terms: dict[str, nn.Module] = field(default_factory=dict)
    #: log the loss's other scalar entries (a plugin's loss; ClipPPOLoss's own diagnostics are left out as before)
    plugin_metrics: bool = False
    #: what the SAC loop has and this one does not (a trainer asks every family's components the same)
    replay_buffer: None = None
    adapter: None = None
    warm_start: None = None
    rank_events: None = None

    @property
    def double_sampling(self) -> DoubleSamplingTransform | None:
        """RNAC-DS's transform when the algorithm's env hook added one (its counters and generator are checkpointed)."""
        return self.env_transform if isinstance(self.env_transform, DoubleSamplingTransform) else None

    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        named = {f"actor.{k}": p for k, p in self.modules.actor.named_parameters()}
        named.update({f"critic.{k}": p for k, p in self.modules.critic.named_parameters()})
        return named

    def _own_state(self) -> dict:
        ds = self.double_sampling
        return {
            "actor": self.modules.actor.state_dict(),
            "critic": self.modules.critic.state_dict(),
            "reward_scaler": self.reward_scaler.state_dict() if self.reward_scaler is not None else None,
            "ds_rng": repr(ds.rng_state()) if ds is not None else None,
            "ds_counts": [ds.worst_picks, ds.steps] if ds is not None else None,
        }

    def _load_networks(self, state: dict) -> None:
        self.modules.actor.load_state_dict(state["actor"])
        self.modules.critic.load_state_dict(state["critic"])

    def _load_own_state(self, state: dict) -> None:
        if self.reward_scaler is not None and state.get("reward_scaler") is not None:
            self.reward_scaler.load_state_dict(state["reward_scaler"])
        ds = self.double_sampling
        if ds is not None and state.get("ds_rng"):
            ds.set_rng_state(ast.literal_eval(state["ds_rng"]))
        if ds is not None and state.get("ds_counts") is not None:
            ds.worst_picks, ds.steps = (int(v) for v in state["ds_counts"])


class LinearDecay:
    """``1 - step / total`` (floored at 0): the original trainer's linear LR decay, as a picklable object so that
    ``LambdaLR.state_dict()`` saves it.

    >>> LinearDecay(4)(1), LinearDecay(4)(8)
    (0.75, 0.0)
    """

    def __init__(self, total: int) -> None:
        self.total = max(1, int(total))

    def __call__(self, step: int) -> float:
        return max(0.0, 1.0 - step / self.total)


def _net(in_dim: int, out_dim: int, mlp, algorithm, action_dim: int, obs_norm: RunningObsNorm | None, device):
    body = make_recipe_mlp(in_dim, out_dim, mlp, algorithm, action_dim, device)
    init_network(body, mlp)
    return nn.Sequential(obs_norm, body) if obs_norm is not None else body


def make_ppo_modules(recipe, env) -> PPOModules:
    """Actor (``algorithm.ppo.policy``: RNAC's clipped Gaussian or TorchRL's tanh-Gaussian, both with a
    state-independent log-std), state-value critic, ``ClipPPOLoss`` and GAE (or RNAC-IPM's shifted GAE) from a
    recipe's ``network`` and ``algorithm`` sections."""
    device = torch.device(recipe.device)
    alg, ppo = recipe.algorithm, recipe.algorithm.ppo
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = action_spec(env)
    act_dim = spec.shape[-1]
    norms = [RunningObsNorm(obs_dim).to(device), RunningObsNorm(obs_dim).to(device)] if ppo.obs_norm else []
    a, c = recipe.network.actor, recipe.network.critic
    actor_body = _net(obs_dim, act_dim, a, alg, act_dim, norms[0] if norms else None, device)
    low, high = spec.space.low, spec.space.high
    if ppo.policy == "clipped_gaussian":  # RNAC's: mean = tanh into the box, samples clipped to it
        head, dist_class = [BoxTanh(low, high).to(device)], ClippedNormal
    else:  # TorchRL's tanh-squashed Gaussian
        head, dist_class = [], TanhNormal
    policy = TensorDictModule(
        nn.Sequential(actor_body, *head, AddStateIndependentNormalScale(act_dim, scale_lb=1e-8).to(device)),
        in_keys=["observation"],
        out_keys=["loc", "scale"],
    )
    actor = ProbabilisticActor(
        policy,
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=dist_class,
        distribution_kwargs={"low": low, "high": high},
        return_log_prob=True,
    )
    critic = ValueOperator(
        _net(obs_dim, 1, c, alg, act_dim, norms[1] if norms else None, device), in_keys=["observation"]
    )
    # 'batch' standardises once per collected batch in PPOTrainer's iteration; 'minibatch' inside the loss
    # algorithm.name's loss (a plugin on the PPO loop: ClipPPOLoss's arguments plus its algorithm.options)
    spec = plugins.algorithm(alg.name)
    loss_class = spec.loss_class()
    loss = loss_class(
        actor,
        critic,
        clip_epsilon=ppo.clip_epsilon,
        entropy_bonus=ppo.entropy_coeff > 0,
        entropy_coeff=ppo.entropy_coeff,
        critic_coeff=ppo.critic_coeff,
        loss_critic_type="l2",
        normalize_advantage=ppo.normalize_advantage == "minibatch",
        functional=False,
        **(dict(alg.options) if spec.options_to_loss else {}),
    )
    make_advantage = spec.hook("advantage")  # RNAC-IPM's shifted GAE; plain GAE when the algorithm has no hook
    if make_advantage is not None:
        advantage = make_advantage(recipe, critic)
    else:
        advantage = GAE(gamma=alg.gamma, lmbda=ppo.gae_lambda, value_network=critic, average_gae=False)
    return PPOModules(actor, critic, loss, advantage, norms)


def make_recipe_ppo_actor(recipe, env):
    """The PPO actor of a recipe for ``env``'s specs (the ``ppo`` family's actor: :func:`adarl.load_policy`, ``adarl
    export``)."""
    return make_ppo_modules(recipe, env).actor


def build_ppo_components(recipe) -> PPOComponents:
    """Env (+ RNAC-DS), evaluation env, networks, loss, optimisers, LR decay and collector of a PPO recipe (a recipe
    on another loop is refused, naming its builder: :func:`adarl.runtime.families.check_builder`)."""
    check_builder(recipe, build_ppo_components)
    check_device(recipe.device)
    apply_num_threads(recipe)
    seed_everything(recipe.seed)
    env, eval_env = make_envs(recipe)
    modules = make_ppo_modules(recipe, env)
    alg, ppo = recipe.algorithm, recipe.algorithm.ppo
    make_transform = plugins.algorithm(alg.name).hook("env_transform")  # RNAC-DS's double sampling
    transform = make_transform(recipe, modules.critic) if make_transform is not None else None
    if transform is not None:
        env.append_transform(transform)
    optimizers = {
        "actor": torch.optim.Adam(modules.actor.parameters(), lr=alg.lr, eps=ppo.adam_eps),
        "critic": torch.optim.Adam(modules.critic.parameters(), lr=alg.lr, eps=ppo.adam_eps),
    }
    c = recipe.collector
    iterations = math.ceil(c.total_frames / c.frames_per_batch)
    schedulers = {
        k: torch.optim.lr_scheduler.LambdaLR(o, LinearDecay(iterations if ppo.lr_decay else 10**12))
        for k, o in optimizers.items()
    }
    collector = Collector(  # (no recurrent state: the env is left as it is, without TorchRL 0.14's FutureWarning)
        env,
        modules.actor,
        frames_per_batch=c.frames_per_batch,
        total_frames=-1,
        device=recipe.device,
        auto_register_policy_transforms=False,
    )
    terms = registry.loss_terms(modules.loss, alg)
    scaler = RewardScaler(alg.gamma) if ppo.reward_scaling else None
    generator = torch.Generator().manual_seed(recipe.seed + 1)
    return PPOComponents(
        recipe,
        env,
        eval_env,
        modules,
        optimizers,
        schedulers,
        collector,
        scaler,
        transform,
        iterations,
        generator,
        terms,
        plugin_metrics=type(modules.loss) is not ClipPPOLoss,
    )


def simulator_steps_per_frame(recipe) -> int:
    """Environment steps the simulator takes per collected frame: ``m + 1`` for RNAC-DS (it probes ``m`` noisy
    candidates before the real step), 1 otherwise."""
    alg = recipe.algorithm
    return plugins.algorithm(alg.name).steps_per_frame(alg.options)
