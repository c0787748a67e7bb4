"""What every recipe builds the same way: the device check, the MLP of a ``network.<net>`` section, the Q(s, a)
critic the off-policy families share (:func:`make_sac_critic`: SAC's and TD3's), the training and evaluation envs,
and the specs an actor is built from (an env's, or a checkpoint's without an env).

The MLP builder is generic: a plain TorchRL ``MLP``, an :func:`~adarl.core.lowrank.low_rank_mlp`, or, when a
registered baseline asks for a variant (:mod:`adarl.baselines.registry`), that variant's builder.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable, Sequence
from types import SimpleNamespace

import torch
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded
from torchrl.envs import TransformedEnv
from torchrl.modules import MLP, ValueOperator

from adarl.baselines import registry
from adarl.core.lowrank import low_rank_mlp
from adarl.envs.factory import dynamics_state_dict, load_dynamics_state_dict, make_env, make_eval_env
from adarl.envs.obs_norm import (
    find_observation_norm,
    load_obs_norm_state_dict,
    obs_norm_state_dict,
    observation_affine,
    share_observation_norm,
    with_observation_norm,
)
from adarl.envs.state import env_state_dict, gym_rng_state_dict, load_env_state_dict, load_gym_rng_state_dict
from adarl.errors import AdaRLValueError
from adarl.fast.collector import LeanCollector
from adarl.runtime.state import collector_state_dict, load_collector_state_dict

__all__ = [
    "RunComponents",
    "ACTIVATIONS",
    "apply_num_threads",
    "check_device",
    "make_mlp",
    "make_recipe_mlp",
    "recipe_mlp_kwargs",
    "init_network",
    "action_spec",
    "is_discrete",
    "make_sac_critic",
    "train_env_factory",
    "make_envs",
    "check_spaces",
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


def recipe_mlp_kwargs(mlp, algorithm, action_dim: int, device) -> dict:
    """:func:`make_mlp`'s keyword arguments for a recipe's ``network.<net>`` section (``mlp``): its widths,
    activation and low-rank layers, plus the variants the registered baselines ask for given the ``algorithm``
    section (every family's actor and critic builder reads a section through this one function)."""
    return dict(
        num_cells=mlp.num_cells,
        activation=mlp.activation,
        low_rank_layers=mlp.low_rank_layers,
        rank=mlp.rank,
        device=torch.device(device),
        **registry.network_kwargs(mlp, algorithm, action_dim),
    )


def make_recipe_mlp(in_features: int, out_features: int, mlp, algorithm, action_dim: int, device) -> nn.Module:
    """The MLP of a recipe's ``network.<net>`` section (``mlp``), with the variants the registered baselines ask
    for given the ``algorithm`` section; its initial weights are each layer's own (see :func:`init_network`)."""
    return make_mlp(in_features, out_features, **recipe_mlp_kwargs(mlp, algorithm, action_dim, device))


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


def make_sac_critic(env, obs_key="observation", **mlp_kwargs) -> ValueOperator:
    """Q(s, a) for boxes (input ``[s, a]``), or Q(s, .) over all actions for discrete specs: SAC's critic, which
    TD3 and DDPG share (here, so that no family's builder imports another's)."""
    obs_dim = env.observation_spec[obs_key].shape[-1]
    spec = action_spec(env)
    if is_discrete(spec):
        net = make_mlp(obs_dim, spec.space.n, **mlp_kwargs)
        return ValueOperator(net, in_keys=[obs_key], out_keys=["action_value"])
    net = make_mlp(obs_dim + spec.shape[-1], 1, **mlp_kwargs)
    return ValueOperator(net, in_keys=[obs_key, "action"])


def _env_kwargs(recipe) -> dict:
    e = recipe.env
    p = e.perturbation
    return dict(
        mode=p.mode,
        dynamics_key=p.key,
        device=recipe.device,
        max_episode_steps=e.max_episode_steps,
        parameters=e.declared(),
        normalize_observations=e.normalize_observations,
    )


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


def check_spaces(recipe, env) -> None:
    """Refuse, naming why, an env whose spaces the recipe's networks cannot read or act in (any gymnasium id
    reaches here): one flat vector ``"observation"``, and a 1-D box of actions (a discrete one on the ``sac`` loop,
    DiscreteSACLoss, only)."""
    e = recipe.env
    obs = env.observation_spec["observation"] if "observation" in env.observation_spec.keys() else None
    if obs is None or len(obs.shape) - len(env.batch_size) != 1:
        found = {str(k): list(v.shape) for k, v in env.observation_spec.items() if str(k) != e.perturbation.key}
        raise AdaRLValueError(
            f"env.id {e.id!r}: adarl's networks read one flat vector 'observation' (a 1-D Box observation space); "
            f"this env's observations are {found} (flatten them with a gymnasium wrapper in an env of your own, "
            "gymnasium.register)"
        )
    spec = action_spec(env)
    base = recipe.algorithm.base
    if is_discrete(spec):
        if base != "sac":
            raise AdaRLValueError(
                f"env.id {e.id!r} has discrete actions ({type(spec).__name__}, {int(spec.space.n)} choices); "
                f"algorithm.name {recipe.algorithm.name!r} (the {base!r} loop) needs a continuous (Box) action space; "
                "allowed for discrete actions: algorithm.name: sac (DiscreteSACLoss)"
            )
        if len(spec.shape) != 1:
            raise AdaRLValueError(f"env.id {e.id!r}: only a single Discrete action space is supported, got {spec}")
        return
    if not isinstance(spec, Bounded) or len(spec.shape) != 1:
        raise AdaRLValueError(
            f"env.id {e.id!r}: its action space ({type(spec).__name__}, shape {list(spec.shape)}) is neither a 1-D "
            "Box nor a Discrete; adarl's actors act in a bounded 1-D box (or, on the sac loop, one Discrete)"
        )


def make_envs(recipe) -> tuple:
    """The training env (perturbed per episode) and the evaluation env (fixed at the nominal dynamics). With
    ``env.normalize_observations`` the evaluation env's normaliser reads the training statistics, frozen."""
    e, p = recipe.env, recipe.env.perturbation
    if e.normalize_observations and recipe.collector.overlap == "process":
        raise AdaRLValueError(
            "env.normalize_observations: true with collector.overlap: 'process': the worker process would keep "
            "observation statistics of its own; allowed with normalisation: collector.overlap false or 'thread'"
        )
    env = train_env_factory(recipe)()
    try:
        check_spaces(recipe, env)
        # Evaluation runs on the nominal dynamics: the centre of the training schedule (or the plain env).
        nominal = (p.schedule if p.schedule is not None else p.preset) if recipe.eval.nominal else "none"
        eval_env = make_eval_env(e.id, nominal, seed=recipe.seed + 10_000, **_env_kwargs(recipe))
    except BaseException:
        env.close()
        raise
    if e.normalize_observations:
        share_observation_norm(env, eval_env)
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
    """What every family's component bundle shares: the policy the collector runs, a close that shuts the collector
    and both envs once, and its own checkpoint state (:meth:`state_dict` / :meth:`load_state_dict`), so that a
    trainer saves and loads a run without knowing what its family built.

    Subclasses are dataclasses with ``modules``, ``optimizers``, ``schedulers``, ``collector``, ``env``,
    ``eval_env``, ``sampling_generator``, and ``replay_buffer``, ``adapter``, ``warm_start``, ``rank_events``
    (None where the family has none); they say what else they hold (:meth:`guarded_parameters`,
    :meth:`_own_state`, :meth:`_load_networks`, :meth:`_load_own_state`)."""

    @property
    def policy(self):
        """The stochastic policy the collector runs (the same parameter objects as the loss's actor)."""
        return self.modules.actor

    def raw_observation_actor(self):
        """The actor for raw observations: ``modules.actor`` itself, or, with ``env.normalize_observations``, a
        copy whose network first applies the training statistics as they are now (frozen: what
        :func:`adarl.load_policy` gives), for an env without the normaliser (sweeps, your own code)."""
        if find_observation_norm(self.env) is None:
            return self.modules.actor
        return with_observation_norm(copy.deepcopy(self.modules.actor), observation_affine(self.env))

    def close(self) -> None:
        """Shut the collector down and close the envs (each only once)."""
        for closable in (self.collector, self.env, self.eval_env):
            try:
                closable.shutdown() if hasattr(closable, "shutdown") else closable.close()
            except Exception:  # noqa: BLE001 - already closed
                pass

    # ------------------------------------------------------------------ what a family provides
    def guarded_parameters(self) -> dict[str, torch.Tensor]:
        """``{readable name: tensor}`` of every trained parameter the divergence guard checks."""
        raise NotImplementedError

    def _own_state(self) -> dict:
        """The checkpoint entries only this family has (networks, loss, adapter, ...)."""
        raise NotImplementedError

    def _load_networks(self, state: dict) -> None:
        """Load the networks of :meth:`_own_state` (before the optimisers: their state follows the shapes)."""
        raise NotImplementedError

    def _load_own_state(self, state: dict) -> None:
        """Load the rest of :meth:`_own_state` (after the optimisers and schedules)."""

    # ------------------------------------------------------------------ checkpoint state
    def state_dict(self) -> dict:
        """Everything the components hold that a run continues from: the family's own entries, optimisers, schedules,
        the live episode (dynamics, simulator and gymnasium state, the collector's carrier and counters), the
        evaluation env's generators, the sampling generator, and the specs :func:`adarl.load_policy` builds the
        actor from. A lean collector's prefetched batch is finished first (it moves the env)."""
        if isinstance(self.collector, LeanCollector):
            self.collector.drain(keep=True)
        return {
            **self._own_state(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
            "dynamics": dynamics_state_dict(self.env),
            "sampling_rng": self.sampling_generator.get_state(),
            "env_state": env_state_dict(self.env),
            "collector": collector_state_dict(self.collector),
            "eval_rng": gym_rng_state_dict(self.eval_env),
            "policy_specs": policy_specs(self.env),
            "obs_norm": obs_norm_state_dict(self.env),
        }

    def load_state_dict(self, state: dict, *, fill_replay_buffer: Callable[[object], None] | None = None) -> None:
        """Put back what :meth:`state_dict` saved, in the order exact resume needs: networks, optimisers, schedules,
        the family's other state, the replay buffer (``fill_replay_buffer(buffer)``: it lies in the run folder,
        beside the checkpoint), then the live episode and the generators. The global RNGs are the caller's (last)."""
        self._load_networks(state)
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        for k, s in self.schedulers.items():
            s.load_state_dict(state["schedulers"][k])
        self._load_own_state(state)
        if fill_replay_buffer is not None and self.replay_buffer is not None:
            fill_replay_buffer(self.replay_buffer)
        load_dynamics_state_dict(self.env, state["dynamics"])
        load_obs_norm_state_dict(self.env, state.get("obs_norm"))  # in place: the evaluation env shares them
        live_episode = load_env_state_dict(self.env, state.get("env_state"))
        if state.get("collector") is not None:
            load_collector_state_dict(self.collector, state["collector"], carrier=live_episode)
        load_gym_rng_state_dict(self.eval_env, state.get("eval_rng"))
        self.sampling_generator.set_state(state["sampling_rng"])
