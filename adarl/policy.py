"""A trained run's policy as a TorchRL actor, for your own code: :func:`load_policy`.

Resuming a run to get at its actor rebuilds the whole training stack (envs, replay buffer loaded from disk,
collector, optimisers: seconds and gigabytes). The actor needs far less: the recipe's network section, the
observation and action specs (saved in every checkpoint as ``policy_specs``), and the actor's tensors. Layers a
rank event truncated are given the checkpoint's ranks before the tensors are loaded.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import torch

from adarl.errors import AdaRLValueError, CheckpointError

__all__ = ["load_policy", "policy_specs", "LoadedPolicy", "load_policy_with_info", "WHICH"]

#: the checkpoints of a run folder ``load_policy`` can load
WHICH = ("latest", "best")
_ACTOR_PREFIX = "actor_network_params."


def policy_specs(env) -> dict:
    """What building the actor takes from ``env``, as plain values and tensors (a checkpoint stores it): the
    observation size and the action box (``action_low``/``action_high``) or the number of discrete actions."""
    from torchrl.data import Categorical, OneHot

    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    out = {"observation_dim": int(env.observation_spec["observation"].shape[-1])}
    if isinstance(spec, (OneHot, Categorical)):
        out.update(action_kind="one_hot" if isinstance(spec, OneHot) else "categorical", action_n=int(spec.space.n))
    else:
        out.update(action_kind="box", action_low=spec.space.low.detach().cpu().clone(),
                   action_high=spec.space.high.detach().cpu().clone())
    return out


def _specs_from_env_id(env_id: str) -> dict:
    """For checkpoints written before they held ``policy_specs``: the spaces of the gymnasium env (its model is
    built, no TorchRL env, buffer or collector)."""
    from adarl.envs import LINEAR_CARTPOLE_ID, LinearCartPoleEnv, quiet_mujoco

    if env_id == LINEAR_CARTPOLE_ID:
        return policy_specs(LinearCartPoleEnv())
    import gymnasium as gym

    with quiet_mujoco():
        env = gym.make(env_id)
    try:
        obs, act = env.observation_space, env.action_space
        out = {"observation_dim": int(obs.shape[-1])}
        if isinstance(act, gym.spaces.Discrete):
            out.update(action_kind="one_hot", action_n=int(act.n))  # TorchRL's GymEnv default encoding
        else:
            out.update(action_kind="box", action_low=torch.as_tensor(act.low, dtype=torch.float32),
                       action_high=torch.as_tensor(act.high, dtype=torch.float32))
        return out
    finally:
        env.close()


def _spec_env(specs: dict, device) -> SimpleNamespace:
    """An object with the two specs the actor builders read (``observation_spec``, ``action_spec``)."""
    from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded

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


@dataclass
class LoadedPolicy:
    """:func:`load_policy_with_info`'s answer: the actor and where it came from."""

    actor: torch.nn.Module
    recipe: object
    run_dir: Path
    checkpoint: Path
    frames: int


def _checkpoint(path: str | os.PathLike, which: str):
    from adarl.run_dir import RunDir

    if which not in WHICH:
        raise AdaRLValueError(f"which must be one of {list(WHICH)}, got {which!r}")
    p = Path(path)
    if p.is_dir():
        run = RunDir.open(p)
        if which == "best":
            ckpt = run.best_checkpoint_path
            if not ckpt.is_file():
                raise CheckpointError(f"{str(p)!r} has no best checkpoint ({ckpt.name}: written at evaluations "
                                      f"when checkpoint.keep_best is true); load which='latest' instead")
            return run, ckpt, run.load_checkpoint(ckpt)
        ckpts = run.checkpoints()
        if not ckpts:
            raise CheckpointError(f"{str(p)!r} has no checkpoint to load the policy from (checkpoints/ckpt-*.pt)")
        state = run.load_latest_checkpoint()
        frames = int(state["counters"]["frames"])
        ckpt = next((c for c in reversed(ckpts) if c.name == f"ckpt-{frames:012d}.pt"), ckpts[-1])
        return run, ckpt, state
    if p.is_file():
        folder = p.parent.parent if p.parent.name == "checkpoints" else p.parent
        if not (folder / "recipe.yaml").is_file():
            raise CheckpointError(f"checkpoint {str(p)!r}: its run folder's recipe.yaml (the network it holds) was "
                                  f"not found at {str(folder / 'recipe.yaml')!r}; load the checkpoint from inside "
                                  f"its run folder (<run>/checkpoints/)")
        run = RunDir.open(folder)
        return run, p, run.load_checkpoint(p)
    raise CheckpointError(f"{str(p)!r} is neither a run folder nor a checkpoint file")


def _resize_low_rank(actor: torch.nn.Module, params: dict) -> None:
    """Give the actor's LowRankLinear layers the checkpoint's ranks (the ``w2`` shapes), so the tensors load."""
    from adarl.lowrank import LowRankLinear

    for name, module in actor.named_modules():
        if not isinstance(module, LowRankLinear):
            continue
        w2 = params.get(f"{name}.w2")
        if w2 is None or int(w2.shape[-2]) == module.rank:
            continue
        rank = int(w2.shape[-2])
        if not 1 <= rank <= module.rank:
            raise CheckpointError(f"the checkpoint's rank {rank} of actor layer {name!r} does not fit the recipe's "
                                  f"network (rank {module.rank}, at most {module.max_rank})")
        module.truncate_(rank)


def load_policy_with_info(run_dir_or_checkpoint: str | os.PathLike, which: str = "latest", *,
                          device: str | torch.device = "cpu") -> LoadedPolicy:
    """:func:`load_policy`, with the recipe, run folder, checkpoint file and frames it was saved at."""
    from adarl.builders import check_device
    from adarl.config import load_recipe

    dev = check_device(device)
    run, ckpt, state = _checkpoint(run_dir_or_checkpoint, which)
    recipe = load_recipe(str(run.recipe_path)).model_copy(update={"device": str(dev)})
    specs = state.get("policy_specs") or _specs_from_env_id(recipe.env.id)
    env = _spec_env(specs, dev)
    if recipe.algorithm.name == "ppo":
        from adarl.training_ppo import make_ppo_modules

        actor = make_ppo_modules(recipe, env).actor
        params = state["actor"]
    else:
        from adarl.builders import make_recipe_actor

        actor = make_recipe_actor(recipe, env)
        params = {k[len(_ACTOR_PREFIX):]: v for k, v in state["loss"].items() if k.startswith(_ACTOR_PREFIX)}
        _resize_low_rank(actor, params)
    try:
        actor.load_state_dict({k: v.to(dev) for k, v in params.items()})
    except RuntimeError as err:
        raise CheckpointError(f"{str(ckpt)!r}: the actor's tensors do not fit the network recipe.yaml describes: "
                              f"{str(err).splitlines()[0]}") from None
    actor.eval().requires_grad_(False)
    return LoadedPolicy(actor, recipe, run.path, ckpt, int(state["counters"]["frames"]))


def load_policy(run_dir_or_checkpoint: str | os.PathLike, which: str = "latest", *,
                device: str | torch.device = "cpu"):
    """The trained policy of a run as a TorchRL actor (a ``ProbabilisticActor``, a ``TensorDictModule``).

    ``run_dir_or_checkpoint``: a run folder (``which="latest"``, its newest loadable checkpoint, or ``"best"``,
    ``checkpoints/best.pt``, the best nominal-dynamics evaluation), or a checkpoint file inside a run folder.
    Layers a rank event truncated get the checkpoint's ranks. No env, replay buffer or collector is built.

    The actor reads ``"observation"`` (float32) and writes ``"action"``; outside ``set_exploration_type`` it acts
    deterministically (the distribution's mode), as the evaluations do. Its parameters do not require grad.
    """
    return load_policy_with_info(run_dir_or_checkpoint, which, device=device).actor
