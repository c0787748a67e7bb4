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

import gymnasium as gym
import torch

from adarl.core.lowrank import LowRankLinear
from adarl.envs.linear_cartpole import LINEAR_CARTPOLE_ID, LinearCartPoleEnv
from adarl.envs.obs_norm import observation_affine, with_observation_norm
from adarl.envs.registry import quiet_mujoco
from adarl.errors import AdaRLValueError, CheckpointError
from adarl.runtime._export_archive import is_export_file
from adarl.runtime.builders.common import check_device, policy_specs, spec_env
from adarl.runtime.families import family
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = ["load_policy", "LoadedPolicy", "load_policy_with_info", "WHICH"]

#: the checkpoints of a run folder ``load_policy`` can load
WHICH = ("latest", "best")


def _specs_from_env_id(env_id: str) -> dict:
    """For checkpoints written before they held ``policy_specs``: the spaces of the gymnasium env (its model is
    built, no TorchRL env, buffer or collector)."""
    if env_id == LINEAR_CARTPOLE_ID:
        return policy_specs(LinearCartPoleEnv())
    with quiet_mujoco():
        env = gym.make(env_id)
    try:
        obs, act = env.observation_space, env.action_space
        out = {"observation_dim": int(obs.shape[-1])}
        if isinstance(act, gym.spaces.Discrete):
            out.update(action_kind="one_hot", action_n=int(act.n))  # TorchRL's GymEnv default encoding
        else:
            out.update(
                action_kind="box",
                action_low=torch.as_tensor(act.low, dtype=torch.float32),
                action_high=torch.as_tensor(act.high, dtype=torch.float32),
            )
        return out
    finally:
        env.close()


@dataclass
class LoadedPolicy:
    """:func:`load_policy_with_info`'s answer: the actor and where it came from."""

    actor: torch.nn.Module
    recipe: object
    run_dir: Path
    checkpoint: Path
    frames: int


def _checkpoint(path: str | os.PathLike, which: str):
    if which not in WHICH:
        raise AdaRLValueError(f"which must be one of {list(WHICH)}, got {which!r}")
    p = Path(path)
    if p.is_dir():
        run = RunDir.open(p)
        if which == "best":
            ckpt = run.best_checkpoint_path
            if not ckpt.is_file():
                raise CheckpointError(
                    f"{str(p)!r} has no best checkpoint ({ckpt.name}: written at evaluations "
                    f"when checkpoint.keep_best is true); load which='latest' instead"
                )
            return run, ckpt, run.load_checkpoint(ckpt, replay_buffer=False)
        ckpts = run.checkpoints()
        if not ckpts:
            raise CheckpointError(f"{str(p)!r} has no checkpoint to load the policy from (checkpoints/ckpt-*.pt)")
        state = run.load_latest_checkpoint(replay_buffer=False)  # a policy needs no replay buffer (not read)
        frames = int(state["counters"]["frames"])
        ckpt = next((c for c in reversed(ckpts) if c.name == f"ckpt-{frames:012d}.pt"), ckpts[-1])
        return run, ckpt, state
    if p.is_file():
        if is_export_file(p):  # a zip holding adarl.json: named as what it is (nothing in it is loaded here)
            raise AdaRLValueError(
                f"{str(p)!r} is an exported policy (adarl export), not a checkpoint or run folder: load it with "
                f"adarl.ExportedPolicy({str(p)!r}).predict(obs)"
            )
        folder = p.parent.parent if p.parent.name == "checkpoints" else p.parent
        if not (folder / "recipe.yaml").is_file():
            raise CheckpointError(
                f"checkpoint {str(p)!r}: its run folder's recipe.yaml (the network it holds) was "
                f"not found at {str(folder / 'recipe.yaml')!r}; load the checkpoint from inside "
                f"its run folder (<run>/checkpoints/)"
            )
        run = RunDir.open(folder)
        return run, p, run.load_checkpoint(p, replay_buffer=False)
    raise CheckpointError(f"{str(p)!r} is neither a run folder nor a checkpoint file")


def _resize_low_rank(actor: torch.nn.Module, params: dict) -> None:
    """Give the actor's LowRankLinear layers the checkpoint's ranks (the ``w2`` shapes), so the tensors load."""
    for name, module in actor.named_modules():
        if not isinstance(module, LowRankLinear):
            continue
        w2 = params.get(f"{name}.w2")
        if w2 is None or int(w2.shape[-2]) == module.rank:
            continue
        rank = int(w2.shape[-2])
        if not 1 <= rank <= module.rank:
            raise CheckpointError(
                f"the checkpoint's rank {rank} of actor layer {name!r} does not fit the recipe's "
                f"network (rank {module.rank}, at most {module.max_rank})"
            )
        module.truncate_(rank)


def load_policy_with_info(
    run_dir_or_checkpoint: str | os.PathLike, which: str = "latest", *, device: str | torch.device = "cpu"
) -> LoadedPolicy:
    """:func:`load_policy`, with the recipe, run folder, checkpoint file and frames it was saved at."""
    dev = check_device(device)
    run, ckpt, state = _checkpoint(run_dir_or_checkpoint, which)
    recipe = run.load_recipe().model_copy(update={"device": str(dev)})
    specs = state.get("policy_specs") or _specs_from_env_id(recipe.env.id)
    env = spec_env(specs, dev)
    fam = family(recipe)  # the loop says which actor and where its tensors lie (the loss's, off-policy)
    actor = fam.make_actor(recipe, env)
    params = fam.actor_params(state)
    _resize_low_rank(actor, params)
    try:
        actor.load_state_dict({k: v.to(dev) for k, v in params.items()})
    except RuntimeError as err:
        raise CheckpointError(
            f"{str(ckpt)!r}: the actor's tensors do not fit the network recipe.yaml describes: "
            f"{str(err).splitlines()[0]}"
        ) from None
    if state.get("obs_norm") is not None:  # env.normalize_observations: the checkpoint's statistics, frozen
        with_observation_norm(actor, observation_affine(state["obs_norm"]).to(dev))
    actor.eval().requires_grad_(False)
    return LoadedPolicy(actor, recipe, run.path, ckpt, int(state["counters"]["frames"]))


def load_policy(run_dir_or_checkpoint: str | os.PathLike, which: str = "latest", *, device: str | torch.device = "cpu"):
    """The trained policy of a run as a TorchRL actor (a ``ProbabilisticActor``, a ``TensorDictModule``).

    ``run_dir_or_checkpoint``: a run folder (``which="latest"``, its newest loadable checkpoint, or ``"best"``,
    ``checkpoints/best.pt``, the best nominal-dynamics evaluation), or a checkpoint file inside a run folder.
    Layers a rank event truncated get the checkpoint's ranks. No env, replay buffer or collector is built.

    The actor reads ``"observation"`` (float32) and writes ``"action"``; outside ``set_exploration_type`` it acts
    deterministically (the distribution's mode), as the evaluations do. Its parameters do not require grad. A run
    with ``env.normalize_observations`` gives an actor reading raw observations: its network starts with the
    checkpoint's statistics, frozen (:class:`adarl.envs.ObservationAffine`).
    """
    return load_policy_with_info(run_dir_or_checkpoint, which, device=device).actor
