"""What every recipe builds the same way: the device check, the MLP of a ``network.<net>`` section, the training
and evaluation envs, and the specs an actor is built from (an env's, or a checkpoint's without an env).

The MLP builder is generic: a plain TorchRL ``MLP``, an :func:`~adarl.core.lowrank.low_rank_mlp`, or, when a
registered baseline asks for a variant (:mod:`adarl.baselines.registry`), that variant's builder.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from types import SimpleNamespace

import torch
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import TransformedEnv
from torchrl.modules import MLP

from adarl.baselines import registry
from adarl.core.lowrank import low_rank_mlp
from adarl.envs.factory import make_env, make_eval_env
from adarl.errors import AdaRLValueError

__all__ = [
    "RunComponents",
    "ACTIVATIONS",
    "apply_num_threads",
    "check_device",
    "make_mlp",
    "make_recipe_mlp",
    "init_network",
    "action_spec",
    "is_discrete",
    "train_env_factory",
    "make_envs",
    "policy_specs",
    "spec_env",
]

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
    "elu": nn.ELU,
    "gelu": nn.GELU,
}


def apply_num_threads(recipe) -> None:
    """``torch.set_num_threads(algorithm.num_threads)`` when the recipe sets it (base.yaml: 1, the fastest at
    (64, 64) on CPU; two runs side by side on two cores otherwise fight over each other's threads). Every
    algorithm's builder calls it, so the key means the same for SAC and the PPO loop."""
    threads = recipe.algorithm.num_threads
    if threads is not None:
        torch.set_num_threads(threads)


def check_device(device: str | torch.device) -> torch.device:
    """``torch.device(device)``, or :class:`AdaRLValueError` naming why this machine cannot use it and what it can
    (instead of torch's error deep inside the first tensor put there)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return dev
    if not torch.cuda.is_available():
        why = (
            f"this torch ({torch.__version__}) was built without CUDA"
            if torch.version.cuda is None
            else "no CUDA GPU is visible (torch.cuda.is_available() is False)"
        )
        raise AdaRLValueError(
            f"device {str(device)!r} is not available: {why}; allowed here: 'cpu' (the recipe "
            f"key `device`, e.g. the override device=cpu)"
        )
    n = torch.cuda.device_count()
    if dev.index is not None and dev.index >= n:
        allowed = ", ".join(["'cpu'", "'cuda'", *(f"'cuda:{i}'" for i in range(n))])
        raise AdaRLValueError(
            f"device {str(device)!r} is not available: this machine has {n} CUDA device(s); allowed here: {allowed}"
        )
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
    baselines' network variants, built by the registered variant builder (:mod:`adarl.baselines.registry`).

    >>> net = make_mlp(11, 6, num_cells=(64, 64), low_rank_layers=[0], rank=4)
    >>> type(net[0]).__name__, net[0].rank
    ('LowRankLinear', 4)
    """
    act = _activation(activation)
    if variants:
        return registry.build_variant_network(
            in_features, out_features, num_cells, act, low_rank_layers, rank, device=device, **variants
        )
    if len(low_rank_layers) == 0:
        return MLP(
            in_features=in_features,
            out_features=out_features,
            num_cells=list(num_cells),
            activation_class=act,
            device=device,
        )
    return low_rank_mlp(
        in_features,
        out_features,
        num_cells,
        activation_class=act,
        low_rank_layers=low_rank_layers,
        rank=rank,
        device=device,
    )


def make_recipe_mlp(in_features: int, out_features: int, mlp, algorithm, action_dim: int, device) -> nn.Module:
    """The MLP of a recipe's ``network.<net>`` section (``mlp``), with the variants the registered baselines ask
    for given the ``algorithm`` section; its initial weights are each layer's own (see :func:`init_network`)."""
    return make_mlp(
        in_features,
        out_features,
        num_cells=mlp.num_cells,
        activation=mlp.activation,
        low_rank_layers=mlp.low_rank_layers,
        rank=mlp.rank,
        device=device,
        **registry.network_kwargs(mlp, algorithm, action_dim),
    )


def init_network(network: nn.Module, mlp) -> None:
    """Apply ``network.<net>.init`` (a registered scheme; ``'default'`` keeps each layer's own init) to a network."""
    init = registry.init_scheme(mlp.init.scheme)
    if init is not None:
        init.module(network, gain=mlp.init.gain, head_gain=mlp.init.head_gain)


def action_spec(env):
    """The env's action spec for one environment (unbatched)."""
    return env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec


def is_discrete(spec) -> bool:
    return isinstance(spec, (OneHot, Categorical))


def _env_kwargs(recipe) -> dict:
    e = recipe.env
    p = e.perturbation
    return dict(mode=p.mode, dynamics_key=p.key, device=recipe.device, max_episode_steps=e.max_episode_steps)


def train_env_factory(recipe) -> Callable[[], TransformedEnv]:
    """A picklable callable that builds the training env (a collector worker process builds its own copy)."""
    e, p = recipe.env, recipe.env.perturbation
    return functools.partial(
        make_env,
        e.id,
        preset=p.preset,
        schedule=p.schedule,
        num_envs=e.num_envs,
        parallel=e.parallel,
        seed=recipe.seed,
        **_env_kwargs(recipe),
    )


def make_envs(recipe) -> tuple:
    """The training env (perturbed per episode) and the evaluation env (fixed at the nominal dynamics)."""
    e, p = recipe.env, recipe.env.perturbation
    env = train_env_factory(recipe)()
    # Evaluation runs on the nominal dynamics: the centre of the training schedule (or the plain env).
    nominal = (p.schedule if p.schedule is not None else p.preset) if recipe.eval.nominal else "none"
    eval_env = make_eval_env(e.id, nominal, seed=recipe.seed + 10_000, **_env_kwargs(recipe))
    return env, eval_env


def policy_specs(env) -> dict:
    """What building the actor takes from ``env``, as plain values and tensors (a checkpoint stores it): the
    observation size and the action box (``action_low``/``action_high``) or the number of discrete actions."""
    spec = action_spec(env)
    out = {"observation_dim": int(env.observation_spec["observation"].shape[-1])}
    if is_discrete(spec):
        out.update(action_kind="one_hot" if isinstance(spec, OneHot) else "categorical", action_n=int(spec.space.n))
    else:
        out.update(
            action_kind="box",
            action_low=spec.space.low.detach().cpu().clone(),
            action_high=spec.space.high.detach().cpu().clone(),
        )
    return out


def spec_env(specs: dict, device) -> SimpleNamespace:
    """An object with the two specs the actor builders read (``observation_spec``, ``action_spec``), built from
    :func:`policy_specs`: an actor is built without an env."""
    obs = Composite(observation=Unbounded(shape=(int(specs["observation_dim"]),), device=device))
    kind = specs.get("action_kind", "box")
    if kind == "one_hot":
        action = OneHot(int(specs["action_n"]), device=device)
    elif kind == "categorical":
        action = Categorical(int(specs["action_n"]), device=device)
    else:
        low = torch.as_tensor(specs["action_low"], dtype=torch.float32, device=device)
        high = torch.as_tensor(specs["action_high"], dtype=torch.float32, device=device)
        action = Bounded(low=low, high=high, shape=low.shape, dtype=torch.float32, device=device)
    return SimpleNamespace(observation_spec=obs, action_spec=action, action_spec_unbatched=action)


class RunComponents:
    """What the SAC and PPO component bundles share: the policy the collector runs and a close that shuts the
    collector and both envs once. Subclasses are dataclasses with ``modules``, ``collector``, ``env``, ``eval_env``."""

    @property
    def policy(self):
        """The stochastic policy the collector runs (the same parameter objects as the loss's actor)."""
        return self.modules.actor

    def close(self) -> None:
        """Shut the collector down and close the envs (each only once)."""
        for closable in (self.collector, self.env, self.eval_env):
            try:
                closable.shutdown() if hasattr(closable, "shutdown") else closable.close()
            except Exception:  # noqa: BLE001 - already closed
                pass
