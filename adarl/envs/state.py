"""Snapshots of live environments mid-episode, so a resumed run continues the very episode it was in.

A checkpoint taken between two collector batches usually falls mid-episode. Restarting the episode on resume
would change every later transition, so for an exact resume :func:`env_state_dict` records, per worker:

* the simulator state: MuJoCo's full integration state (``mj_getState(mjSTATE_INTEGRATION)``: time, qpos, qvel,
  act, warm-start accelerations, controls, ...), or a classic-control env's ``state`` array;
* gymnasium's own counters: the ``TimeLimit`` step count and the env's ``np_random`` generator state (it draws
  the next episode's initial state);
* and the current episode's perturbed parameters are re-applied to the model from the perturbation transform's
  restored state (see :func:`load_env_state_dict`).

The TorchRL side (observation, ``episode_reward``, ``step_count``, trajectory ids) lives in the collector's
carrier TensorDict, saved with the collector (:func:`adarl.runtime.state.collector_state_dict`). Everything is plain
tensors, numbers and strings, so it loads with ``torch.load(weights_only=True)``.

Envs in worker processes (``ParallelEnv``) cannot be reached from the trainer: :func:`env_state_dict` returns
None for them and a resumed run starts fresh episodes there (documented in docs/resuming.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torchrl.envs import EnvBase, ParallelEnv, SerialEnv, TransformedEnv

from adarl.envs.factory import perturbation_transform
from adarl.errors import CheckpointError

__all__ = [
    "env_state_dict",
    "load_env_state_dict",
    "gym_rng_state_dict",
    "load_gym_rng_state_dict",
    "exact_resume_supported",
]

_VERSION = 1


def _unbatched_envs(env: EnvBase) -> list[EnvBase] | None:
    """The per-worker TorchRL envs of a ``make_env`` env, or None when they live in other processes."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    if isinstance(base, ParallelEnv):
        return None
    if isinstance(base, SerialEnv):
        base.start() if hasattr(base, "start") and getattr(base, "is_closed", False) else None
        return list(base._envs)
    return [env]


def _gym_chain(env: EnvBase) -> list[Any]:
    """The gymnasium wrappers from the outermost to the unwrapped env."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    gym = getattr(base, "_env", None)
    if gym is None:
        raise CheckpointError(f"cannot snapshot {type(base).__name__}: exact resume needs a torchrl GymEnv")
    chain = [gym]
    while hasattr(chain[-1], "env") and chain[-1] is not getattr(chain[-1], "unwrapped", chain[-1]):
        chain.append(chain[-1].env)
    return chain


def _perturbation(env: EnvBase):
    return perturbation_transform(env) if isinstance(env, TransformedEnv) else None


def exact_resume_supported(env: EnvBase) -> bool:
    """True when every worker's live state can be snapshot (serial envs in this process)."""
    return _unbatched_envs(env) is not None


def _rng_state(gen: np.random.Generator) -> dict:
    return _weights_only_safe(gen.bit_generator.state)


def _weights_only_safe(obj):
    """Numpy scalars/ints (PCG64 state holds 128-bit ints) as plain Python types, loadable with weights_only."""
    if isinstance(obj, dict):
        return {k: _weights_only_safe(v) for k, v in obj.items()}
    if isinstance(obj, (np.integer, int)) and not isinstance(obj, bool):
        return str(int(obj)) if abs(int(obj)) >= 2**63 else int(obj)
    return obj


def _from_weights_only(obj):
    if isinstance(obj, dict):
        return {k: _from_weights_only(v) for k, v in obj.items()}
    if isinstance(obj, str) and obj.lstrip("-").isdigit():
        return int(obj)
    return obj


def _native(env: EnvBase):
    """adarl's own TorchRL envs (e.g. the linear CartPole) snapshot themselves: ``snapshot()``/``restore()``."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    return base if hasattr(base, "snapshot") and hasattr(base, "restore") else None


def _worker_state(env: EnvBase) -> dict:
    native = _native(env)
    if native is not None:
        return {"native": native.snapshot()}
    chain = _gym_chain(env)
    unwrapped = chain[-1]
    state: dict[str, Any] = {"elapsed_steps": None, "np_random": None, "sim": None}
    for w in chain:
        if hasattr(w, "_elapsed_steps"):
            state["elapsed_steps"] = None if w._elapsed_steps is None else int(w._elapsed_steps)
            break
    if getattr(unwrapped, "_np_random", None) is not None:
        state["np_random"] = _rng_state(unwrapped._np_random)
    data, model = getattr(unwrapped, "data", None), getattr(unwrapped, "model", None)
    if data is not None and model is not None and type(data).__module__.startswith("mujoco"):
        import mujoco

        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        buf = np.empty(mujoco.mj_stateSize(model, spec), dtype=np.float64)
        mujoco.mj_getState(model, data, buf, spec)
        state["sim"] = {"kind": "mujoco", "state": torch.from_numpy(buf)}
    elif getattr(unwrapped, "state", None) is not None:
        state["sim"] = {
            "kind": "array",
            "state": torch.as_tensor(np.asarray(unwrapped.state, dtype=np.float64)),
            "steps_beyond_terminated": getattr(unwrapped, "steps_beyond_terminated", None),
        }
    else:
        raise CheckpointError(f"cannot snapshot {type(unwrapped).__name__}: no MuJoCo data and no `state` array")
    return state


def _load_worker_state(env: EnvBase, state: dict) -> None:
    native = _native(env)
    if native is not None:
        native.restore(state["native"])
        return
    chain = _gym_chain(env)
    unwrapped = chain[-1]
    transform = _perturbation(env)
    if transform is not None and transform._values is not None:
        transform.applier.apply(transform._values)  # this episode's dynamics, before its state goes back in
    for w in chain:
        if hasattr(w, "_elapsed_steps"):
            w._elapsed_steps = state["elapsed_steps"]
            break
    for w in chain:  # gymnasium's OrderEnforcing refuses step() before a reset
        if hasattr(w, "_has_reset"):
            w._has_reset = True
    if state["np_random"] is not None:
        # In place: the perturbation transform tells a reseed by the generator object's identity.
        unwrapped.np_random.bit_generator.state = _from_weights_only(state["np_random"])
    sim = state["sim"]
    if sim["kind"] == "mujoco":
        import mujoco

        model, data = unwrapped.model, unwrapped.data
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        buf = sim["state"].numpy()
        if buf.size != mujoco.mj_stateSize(model, spec):
            raise CheckpointError(
                f"saved MuJoCo state has {buf.size} numbers, this model needs "
                f"{mujoco.mj_stateSize(model, spec)} (different env?)"
            )
        mujoco.mj_setState(model, data, buf, spec)
        mujoco.mj_forward(model, data)
    else:
        unwrapped.state = sim["state"].numpy().copy()
        if "steps_beyond_terminated" in sim and hasattr(unwrapped, "steps_beyond_terminated"):
            unwrapped.steps_beyond_terminated = sim["steps_beyond_terminated"]


def env_state_dict(env: EnvBase) -> dict | None:
    """Every worker's mid-episode state (None for envs in worker processes, which cannot be reached)."""
    envs = _unbatched_envs(env)
    if envs is None:
        return None
    return {"version": _VERSION, "workers": [_worker_state(e) for e in envs]}


def load_env_state_dict(env: EnvBase, state: dict | None) -> bool:
    """Put saved worker states back (after the perturbation state is loaded). False when nothing was restored."""
    envs = _unbatched_envs(env)
    if state is None or envs is None:
        return False
    if int(state.get("version", 0)) > _VERSION:
        raise CheckpointError(f"env state version {state.get('version')} is newer than this adarl reads ({_VERSION})")
    if len(state["workers"]) != len(envs):
        raise CheckpointError(f"checkpoint has {len(state['workers'])} env worker(s), this env has {len(envs)}")
    for e, s in zip(envs, state["workers"]):
        _load_worker_state(e, s)
    return True


def gym_rng_state_dict(env: EnvBase) -> list | None:
    """Only the gymnasium generators (for the evaluation env, which always starts from a reset)."""
    envs = _unbatched_envs(env)
    if envs is None:
        return None
    out = []
    for e in envs:
        if _native(e) is not None:
            out.append({"native": _native(e).snapshot()})
            continue
        g = getattr(_gym_chain(e)[-1], "_np_random", None)
        out.append(None if g is None else _rng_state(g))
    return out


def load_gym_rng_state_dict(env: EnvBase, state: list | None) -> None:
    envs = _unbatched_envs(env)
    if state is None or envs is None or len(state) != len(envs):
        return
    for e, s in zip(envs, state):
        if isinstance(s, dict) and "native" in s and _native(e) is not None:
            _native(e).restore(s["native"])
        elif s is not None:
            _gym_chain(e)[-1].np_random.bit_generator.state = _from_weights_only(s)
