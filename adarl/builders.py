"""Builders: actor, critic and SAC loss from a recipe, out of stock TorchRL pieces and :class:`LowRankLinear`.

Each builder takes plain arguments (not the recipe object) so that users composing in Python can call them
directly; :func:`make_sac_modules` is the recipe-facing wrapper.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Categorical, OneHot
from torchrl.envs import EnvBase
from torchrl.modules import MLP, OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import DiscreteSACLoss, SACLoss, SoftUpdate, ValueEstimators

from adarl.errors import AdaRLValueError
from adarl.lowrank import LowRankLinear, low_rank_mlp

__all__ = ["ACTIVATIONS", "check_device", "make_mlp", "make_recipe_actor", "make_sac_actor", "make_sac_critic", "make_sac_loss", "SACModules", "make_sac_modules",
           "reinit_low_rank_ensemble"]

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
    "elu": nn.ELU,
    "gelu": nn.GELU,
}


def check_device(device: str | torch.device) -> torch.device:
    """``torch.device(device)``, or :class:`AdaRLValueError` naming why this machine cannot use it and what it can
    (instead of torch's error deep inside the first tensor put there)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return dev
    if not torch.cuda.is_available():
        why = (f"this torch ({torch.__version__}) was built without CUDA" if torch.version.cuda is None
               else "no CUDA GPU is visible (torch.cuda.is_available() is False)")
        raise AdaRLValueError(f"device {str(device)!r} is not available: {why}; allowed here: 'cpu' (the recipe "
                              f"key `device`, e.g. the override device=cpu)")
    n = torch.cuda.device_count()
    if dev.index is not None and dev.index >= n:
        allowed = ", ".join(["'cpu'", "'cuda'", *(f"'cuda:{i}'" for i in range(n))])
        raise AdaRLValueError(f"device {str(device)!r} is not available: this machine has {n} CUDA device(s); "
                              f"allowed here: {allowed}")
    return dev


def _activation(name: str) -> type[nn.Module]:
    if name not in ACTIVATIONS:
        raise AdaRLValueError(f"unknown activation {name!r}; allowed: {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]


def make_mlp(
    in_features: int,
    out_features: int,
    num_cells: Sequence[int] = (64, 64),
    activation: str = "relu",
    low_rank_layers: Sequence[int] = (0, 1),
    rank: int | None = None,
    device: torch.device | str = "cpu",
    **variants,
) -> nn.Module:
    """An MLP with the chosen hidden layers low-rank (empty ``low_rank_layers`` gives a plain TorchRL MLP).

    ``variants`` (``sparse_layer``, ``sparse_width``, ``sparse_k``, ``diagonal_scale``, ``input_scale``) select the
    baselines' network variants, built by :func:`adarl.baselines.mlp.make_baseline_mlp`."""
    act = _activation(activation)
    if variants:
        from adarl.baselines.mlp import make_baseline_mlp

        return make_baseline_mlp(in_features, out_features, num_cells, act, low_rank_layers, rank, device=device,
                                 **variants)
    if len(low_rank_layers) == 0:
        return MLP(in_features=in_features, out_features=out_features, num_cells=list(num_cells),
                   activation_class=act, device=device)
    return low_rank_mlp(in_features, out_features, num_cells, activation_class=act,
                        low_rank_layers=low_rank_layers, rank=rank, device=device)


def _is_discrete(action_spec) -> bool:
    return isinstance(action_spec, (OneHot, Categorical))


def make_sac_actor(env: EnvBase, obs_key="observation", **mlp_kwargs) -> ProbabilisticActor:
    """SAC's stochastic policy: TanhNormal for boxes, OneHotCategorical for discrete action specs."""
    obs_dim = env.observation_spec[obs_key].shape[-1]
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    if _is_discrete(spec):
        n = spec.space.n
        net = make_mlp(obs_dim, n, **mlp_kwargs)
        module = TensorDictModule(net, in_keys=[obs_key], out_keys=["logits"])
        return ProbabilisticActor(module, in_keys=["logits"], spec=spec, distribution_class=OneHotCategorical,
                                  return_log_prob=False)
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
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    if _is_discrete(spec):
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
) -> SACLoss | DiscreteSACLoss:
    """TorchRL's ``SACLoss`` (or ``DiscreteSACLoss``) with the TD(0) estimator, as TorchRL's reference SAC."""
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    if _is_discrete(spec):
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
        loss = SACLoss(
            actor_network=actor,
            qvalue_network=critic,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=init_alpha,
            fixed_alpha=fixed_alpha,
            target_entropy=target_entropy,
            action_spec=spec,
        )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=gamma)
    reinit_low_rank_ensemble(loss)
    return loss


@torch.no_grad()
def reinit_low_rank_ensemble(loss, network: str = "qvalue_network") -> int:
    """Give every member of a TorchRL Q ensemble's low-rank layers :class:`LowRankLinear`'s own initialisation.

    Why: a TorchRL loss builds its ensemble (``num_qvalue_nets`` copies, ``expand_dim`` in
    ``LossModule.convert_to_functional``) by resampling every stacked parameter uniformly in ``[min, max]`` of the
    template's values. For a dense ``nn.Linear`` that is its own init distribution; for the factors ``W1``, ``W2``
    it is not: the product of two independent uniform factors starts ~2-5x larger than ``nn.Linear`` (64 wide)
    and with its condition number squared. This redraws each member's ``w1``, ``w2`` and bias as a fresh
    ``LowRankLinear`` (a factorised ``nn.Linear`` init) and copies them into the target parameters. Call it right
    after building the loss (``make_sac_loss`` does). Returns how many layers were redrawn.
    """
    params = getattr(loss, f"{network}_params", None)
    module = getattr(loss, network, None)
    if params is None or module is None:
        raise AdaRLValueError(f"{type(loss).__name__} has no {network}_params to re-initialise")
    online = dict(params.flatten_keys(".").items())
    target = getattr(loss, f"target_{network}_params", None)
    target = dict(target.flatten_keys(".").items()) if target is not None else {}
    count = 0
    for name, layer in module.named_modules():
        if not isinstance(layer, LowRankLinear):
            continue
        keys = [f"{name}.{p}" for p in ("w1", "w2", "bias") if getattr(layer, p, None) is not None]
        if not all(k in online for k in keys):
            continue
        members = online[keys[0]].shape[0] if online[keys[0]].dim() == 3 else None
        if members is None:  # not stacked: the layer kept its own init
            continue
        device, dtype = online[keys[0]].device, online[keys[0]].dtype
        for i in range(members):
            fresh = LowRankLinear(layer.in_features, layer.out_features, rank=layer.rank,
                                  bias=layer.bias is not None, device=device, dtype=dtype)
            for k, p in zip(keys, ("w1", "w2", "bias")):
                online[k].data[i].copy_(getattr(fresh, p))
        for k in keys:
            if k in target:
                target[k].data.copy_(online[k].data)
        count += 1
    return count


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
    from adarl.baselines.mlp import variant_kwargs

    a = recipe.network.actor
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    action_dim = spec.space.n if _is_discrete(spec) else spec.shape[-1]
    return make_sac_actor(env, num_cells=a.num_cells, activation=a.activation, low_rank_layers=a.low_rank_layers,
                          rank=a.rank, device=torch.device(recipe.device),
                          **variant_kwargs(a, recipe.algorithm.parseval, action_dim))


def make_sac_modules(recipe, env: EnvBase) -> SACModules:
    """Build actor, critic, loss and target updater from a recipe's ``network`` and ``algorithm`` sections."""
    from adarl.baselines.mlp import variant_kwargs

    device = torch.device(recipe.device)
    a, c = recipe.network.actor, recipe.network.critic
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    action_dim = spec.space.n if _is_discrete(spec) else spec.shape[-1]
    pv = recipe.algorithm.parseval
    actor = make_recipe_actor(recipe, env)
    critic = make_sac_critic(env, num_cells=c.num_cells, activation=c.activation,
                             low_rank_layers=c.low_rank_layers, rank=c.rank, device=device,
                             **variant_kwargs(c, pv, action_dim))
    alg = recipe.algorithm
    loss = make_sac_loss(actor, critic, env, gamma=alg.gamma, num_qvalue_nets=alg.num_qvalue_nets,
                         loss_function=alg.loss_function, init_alpha=alg.init_alpha, fixed_alpha=alg.fixed_alpha,
                         target_entropy=alg.target_entropy)
    # after the loss exists: SACLoss resamples the stacked critics, so each member is drawn in the loss's params
    for network, mlp in (("actor_network", a), ("qvalue_network", c)):
        if mlp.init.scheme == "orthogonal":
            from adarl.baselines.init import orthogonal_init_loss_

            orthogonal_init_loss_(loss, network, gain=mlp.init.gain, head_gain=mlp.init.head_gain)
    updater = SoftUpdate(loss, tau=alg.tau)
    return SACModules(actor=actor, critic=critic, loss=loss, target_updater=updater)
