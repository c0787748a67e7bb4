"""``PerturbedDynamicsEnvTransform``: new dynamics for every episode of a gymnasium environment.

At every reset the transform draws the episode's parameters from a :class:`~adarl.envs.schedules.Schedule`,
applies them to the live model *before* the base environment resets (so the initial state is computed with the
new model), and writes them into the output tensordict under ``(out_key, <param>)`` (float32 scalars) together
with ``(out_key, "episode")`` (int64, this worker's 0-based episode index), at reset and at every step. The
entries are declared in the observation spec, so collectors keep them, but they are not part of
``"observation"``: a policy reading ``"observation"`` never sees them.

Seeding: the transform owns a ``numpy`` Generator. ``transform.set_seed(s)`` seeds it explicitly; otherwise it
follows the seed of the gymnasium environment it wraps (``env.set_seed(s)`` on the TorchRL env reseeds gymnasium,
and the transform reseeds from that seed at its next reset), so stock ``env.set_seed`` makes runs reproducible,
and ``SerialEnv``/``ParallelEnv``, which give each worker its own seed, give each worker its own stream. The stream
is ``SeedSequence(seed, spawn_key=(salt, worker_index))``: independent of gymnasium's own generator (which gets
the same seed) and of the other workers even when they share a seed. Seeding does not reset the episode index.

Workers: with ``num_workers=N`` and ``worker_index=w``, the worker's k-th episode uses the schedule's episode
``w + N * k``. Deterministic schedules (the paper's sinusoids) are thus interleaved: together the N workers sweep
the sequence one environment would, instead of N copies of it. ``(out_key, "episode")`` records ``k``.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import unravel_key
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, Transform, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

from adarl.envs.declared import declared_dict
from adarl.envs.mujoco_appliers import DynamicsApplier, make_applier
from adarl.envs.registry import (
    check_any_env_id,
    check_mode,
    make_schedule,
    parameters_for,
    validate_schedule,
    validate_values,
)
from adarl.envs.schedules import Schedule, as_schedule
from adarl.errors import AdaRLValueError

__all__ = ["PerturbedDynamicsEnvTransform", "find_gym_env", "EPISODE_KEY"]

#: Name of the episode-index entry under the output key.
EPISODE_KEY = "episode"

# Mixed into every seed so the dynamics stream never coincides with gymnasium's own (same-seeded) generator.
_SALT = 0xADA7D1


def _make_rng(seed: int, worker_index: int) -> np.random.Generator:
    seq = np.random.SeedSequence(entropy=int(seed) % (1 << 128), spawn_key=(_SALT, int(worker_index)))
    return np.random.Generator(np.random.PCG64(seq))


def find_gym_env(env: EnvBase) -> Any:
    """The unwrapped gymnasium environment under a TorchRL env (``GymEnv``, possibly inside ``TransformedEnv``).

    Refuses batched envs: the perturbation must live inside each worker (build it in the worker's factory).
    """
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    if isinstance(base, BatchedEnvBase):
        raise AdaRLValueError(
            f"PerturbedDynamicsEnvTransform sits on a batched env ({type(base).__name__}); it must live inside each "
            "worker's env (put it in the env factory passed to SerialEnv/ParallelEnv, as adarl.envs.make_env does)"
        )
    gym_env = getattr(base, "_env", None)
    if gym_env is None and getattr(base, "adarl_native", False):
        gym_env = base  # an adarl TorchRL env (LinearCartPoleEnv): its applier edits it directly
    if gym_env is None:
        raise AdaRLValueError(
            f"PerturbedDynamicsEnvTransform needs a torchrl GymEnv/GymWrapper underneath, got {type(base).__name__}"
        )
    if tuple(base.batch_size) != ():
        raise AdaRLValueError(
            f"PerturbedDynamicsEnvTransform needs an unbatched GymEnv (batch_size []), got batch_size "
            f"{list(base.batch_size)}; use one GymEnv per worker of a SerialEnv/ParallelEnv instead"
        )
    return getattr(gym_env, "unwrapped", gym_env)


class PerturbedDynamicsEnvTransform(Transform):
    """Draw and apply new dynamics at every reset; report them under ``out_key``.

    Args:
        env_id: the gymnasium id of the wrapped env (one of :data:`adarl.envs.SUPPORTED_ENVS`).
        schedule: a :class:`Schedule`, its dict description, or a preset name (``"paper"``, ``"low"``,
            ``"high"``, ``"nominal"``, ``"none"``; see :func:`adarl.envs.make_schedule`).
        mode: ``"consistent"`` (default; mass and inertia follow the geometry) or ``"ompo"`` (geometry only).
        out_key: where the values go (``(out_key, param)``); a string or a tuple for a nested key.
        seed: seeds the transform's own generator now (else it follows the wrapped gymnasium env's seed).
        worker_index, num_workers: this env's place among the workers of a batched env (see module docs).
        parameters: parameters declared on the env's MuJoCo model fields (a recipe's ``env.parameters``:
            ``{name: {field, index?, low?, high?}}``, :mod:`adarl.envs.declared`), which ``schedule`` may set.

    >>> from torchrl.envs import GymEnv
    >>> env = TransformedEnv(GymEnv("Hopper-v5"), PerturbedDynamicsEnvTransform("Hopper-v5", "paper", seed=0))
    >>> first, second = env.reset()["dynamics"], env.reset()["dynamics"]  # new dynamics at every reset
    >>> sorted(first.keys()), int(first["episode"]), int(second["episode"])
    (['episode', 'foot_length', 'torso_length'], 0, 1)
    >>> bool(first["torso_length"] != second["torso_length"])
    True
    >>> env.close()
    """

    def __init__(
        self,
        env_id: str,
        schedule: Schedule | Mapping | str = "paper",
        *,
        mode: str = "consistent",
        out_key: str | tuple[str, ...] = "dynamics",
        seed: int | None = None,
        worker_index: int = 0,
        num_workers: int = 1,
        parameters: Mapping[str, Any] | None = None,
    ) -> None:
        env_id = check_any_env_id(env_id)
        mode = check_mode(mode)
        declared = declared_dict(parameters)
        if isinstance(schedule, str):
            schedule = make_schedule(env_id, schedule)
        schedule = validate_schedule(env_id, as_schedule(schedule), declared)
        for what, value, least in (("worker_index", worker_index, 0), ("num_workers", num_workers, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise AdaRLValueError(f"{what} must be an integer >= {least}, got {value!r}")
        if worker_index >= num_workers:
            raise AdaRLValueError(f"worker_index must be in [0, num_workers={num_workers}), got {worker_index}")
        if isinstance(out_key, str):
            out_key = (out_key,)
        if not isinstance(out_key, tuple) or not out_key or not all(isinstance(k, str) and k for k in out_key):
            raise AdaRLValueError(f"out_key must be a non-empty string or tuple of strings, got {out_key!r}")
        params = tuple(schedule.params)
        super().__init__(in_keys=[], out_keys=[unravel_key((*out_key, p)) for p in (*params, EPISODE_KEY)])
        self.env_id = env_id
        self.mode = mode
        self.declared = declared
        self.schedule = schedule
        self.params: tuple[str, ...] = params
        self.worker_index = worker_index
        self.num_workers = num_workers
        self.out_key: tuple[str, ...] = out_key
        self._episode = 0  # index of the next episode this worker draws
        self._current_episode = -1
        self._values: dict[str, float] | None = None
        self._rng: np.random.Generator | None = None
        self._seed: int | None = None
        self._env_seen: tuple[Any, int | None] | None = None
        self._applier: DynamicsApplier | None = None
        self._pending = False
        self._out: TensorDictBase | None = None
        if seed is not None:
            self.set_seed(seed)

    # ------------------------------------------------------------------------------------------------ seeding
    def set_seed(self, seed: int) -> None:
        """Seed the dynamics generator explicitly (a later reseed of the wrapped env reseeds it again)."""
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise AdaRLValueError(f"seed must be an integer, got {seed!r}")
        self._seed = int(seed)
        self._rng = _make_rng(self._seed, self.worker_index)
        self._env_seen = self._env_seed_state()

    _set_seed = set_seed

    def _env_seed_state(self) -> tuple[Any, int | None] | None:
        """``(generator, seed)`` of the wrapped gymnasium env, or None when it cannot be reached.

        gymnasium replaces its generator object on every ``reset(seed=...)``, so the object's identity tells a
        reseed apart even when the seed value repeats. ``seed`` is None when unknown (gymnasium's -1).
        """
        try:
            parent = self.parent
            if parent is None:
                return None
            unwrapped = find_gym_env(parent)
        except AdaRLValueError:
            return None
        seed = getattr(unwrapped, "np_random_seed", None)  # initialises gymnasium's generator if needed
        generator = getattr(unwrapped, "_np_random", None)
        seed = int(seed) if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0 else None
        return generator, seed

    def _sync_seed(self) -> None:
        state = self._env_seed_state()
        if state is not None and (self._env_seen is None or state[0] is not self._env_seen[0]):
            first = self._env_seen is None
            self._env_seen = state
            # On first sight an explicit seed (or a loaded state) wins; any later reseed of the env wins.
            if state[1] is not None and not (first and self._rng is not None):
                self._seed = state[1]
                self._rng = _make_rng(state[1], self.worker_index)
        if self._rng is None:  # never seeded and the env's seed is unknown: fresh OS entropy (not reproducible)
            self._rng = np.random.Generator(
                np.random.PCG64(np.random.SeedSequence(spawn_key=(_SALT, self.worker_index)))
            )

    # ------------------------------------------------------------------------------------------------ dynamics
    @property
    def applier(self) -> DynamicsApplier:
        if self._applier is None:
            if self.parent is None:
                raise AdaRLValueError(
                    "PerturbedDynamicsEnvTransform is not attached to an env: use TransformedEnv(GymEnv(...), it)"
                )
            unwrapped = find_gym_env(self.parent)
            live_id = getattr(getattr(unwrapped, "spec", None), "id", None)
            if live_id is not None and live_id != self.env_id:
                raise AdaRLValueError(
                    f"PerturbedDynamicsEnvTransform was built for {self.env_id!r} but wraps {live_id!r}; "
                    f"pass env_id={live_id!r} (supported ids: see adarl.envs.SUPPORTED_ENVS)"
                )
            self._applier = make_applier(self.env_id, unwrapped, self.params, self.mode, self.declared)
        return self._applier

    @property
    def episode(self) -> int:
        """This worker's index of the current episode (-1 before the first reset)."""
        return self._current_episode

    @property
    def values(self) -> dict[str, float]:
        """The current episode's parameter values (the env defaults before the first reset)."""
        if self._values is None:  # a declared parameter's default is the model's own, nan before the first reset
            defaults = parameters_for(self.env_id, self.declared)
            return {p: defaults[p].default for p in self.params}
        return dict(self._values)

    def schedule_index(self, episode: int) -> int:
        """The schedule's episode index for this worker's ``episode``."""
        return self.worker_index + self.num_workers * int(episode)

    def _draw(self) -> None:
        self._sync_seed()
        episode = self._episode
        values = self.schedule.sample(self.schedule_index(episode), self._rng)
        values = validate_values(self.env_id, values, self.declared)
        self.applier.apply(values)
        self._values = values
        self._current_episode = episode
        self._episode = episode + 1
        self._out = None

    def _output(self) -> TensorDictBase:
        if self._out is None:
            parent = self.parent
            device = parent.device if parent is not None else None
            values = self.values
            data = {p: torch.tensor(values[p], dtype=torch.float32, device=device) for p in self.params}
            data[EPISODE_KEY] = torch.tensor(self._current_episode, dtype=torch.int64, device=device)
            self._out = TensorDict(data, batch_size=[], device=device)
        return self._out

    def _write(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_key if len(self.out_key) > 1 else self.out_key[0], self._output().clone())
        return tensordict

    # ------------------------------------------------------------------------------------------------ hooks
    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase | None:
        # Called by TransformedEnv._reset *before* the base env resets: apply the new model first.
        self._draw()
        self._pending = True
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if not self._pending:  # reset reached us without the pre-reset hook: apply now
            self._draw()
        self._pending = False
        return self._write(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._write(next_tensordict)

    def set_container(self, container) -> None:
        """Attach to an env (TorchRL calls this); a batched env is refused here, where it is built, not at its first
        reset: the transform edits one MuJoCo model and must live inside each worker's env."""
        super().set_container(container)
        parent = self.parent
        if parent is not None:
            find_gym_env(parent)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # As TorchRL's env-only transforms: outside an env (a replay buffer, a module) there are no dynamics to draw.
        raise AdaRLValueError(
            "PerturbedDynamicsEnvTransform cannot be executed without a parent environment (it draws and applies "
            "dynamics at each reset of the env it is attached to): use it in TransformedEnv(GymEnv(...), ...)"
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape, device = observation_spec.shape, observation_spec.device
        leaves = {p: Unbounded(shape=shape, dtype=torch.float32, device=device) for p in self.params}
        leaves[EPISODE_KEY] = Unbounded(shape=shape, dtype=torch.int64, device=device)
        first = self.out_key[0]
        if first in observation_spec.keys() and (
            len(self.out_key) == 1
            or not isinstance(observation_spec[first], Composite)
            or self.out_key in observation_spec.keys(True)
        ):
            raise AdaRLValueError(
                f"out_key {self.out_key!r} collides with an existing observation entry; pick another key "
                f"(existing: {sorted(str(k) for k in observation_spec.keys())})"
            )
        node = observation_spec
        for key in self.out_key[:-1]:
            if key not in node.keys():
                node[key] = Composite(shape=shape, device=device)
            node = node[key]
        node[self.out_key[-1]] = Composite(leaves, shape=shape, device=device)
        return observation_spec

    # ------------------------------------------------------------------------------------------------ state
    def get_extra_state(self) -> dict:
        """Episode index and RNG state (plain Python types: safe for ``torch.load(weights_only=True)``)."""
        return {
            "version": 1,
            "env_id": self.env_id,
            "schedule": self.schedule.to_dict(),
            "episode": self._episode,
            "current_episode": self._current_episode,
            "values": None if self._values is None else dict(self._values),
            "seed": self._seed,
            "rng_state": None if self._rng is None else copy.deepcopy(self._rng.bit_generator.state),
        }

    def set_extra_state(self, state: Any) -> None:
        if not isinstance(state, Mapping) or state.get("version") != 1:
            raise AdaRLValueError(f"not a PerturbedDynamicsEnvTransform state (version 1): {state!r}")
        if state.get("env_id") != self.env_id:
            raise AdaRLValueError(f"state is for env {state.get('env_id')!r}, this transform is for {self.env_id!r}")
        self._episode = int(state["episode"])
        self._current_episode = int(state.get("current_episode", self._episode - 1))
        self._values = None if state.get("values") is None else dict(state["values"])
        self._seed = state.get("seed")
        if state.get("rng_state") is not None:
            rng = np.random.Generator(np.random.PCG64())
            rng.bit_generator.state = copy.deepcopy(state["rng_state"])
            self._rng = rng
            # The loaded generator wins over the env's current seed; a later env.set_seed still reseeds.
            self._env_seen = self._env_seed_state()
        else:  # saved before its first draw: follow the env's seed, as the saved transform would have
            self._rng = None
            self._env_seen = None
        self._out = None

    # ------------------------------------------------------------------------------------------------ misc
    def clone(self) -> PerturbedDynamicsEnvTransform:
        other = super().clone()
        other.__dict__["_applier"] = None
        other.__dict__["_rng"] = copy.deepcopy(self._rng)
        other.__dict__["_env_seen"] = None
        other.__dict__["_out"] = None
        other.__dict__["_pending"] = False
        return other

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_applier"] = None  # holds MuJoCo objects; rebuilt on first use
        state["_env_seen"] = None
        return state

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env_id={self.env_id!r}, schedule={self.schedule!r}, mode={self.mode!r}, "
            f"out_key={self.out_key if len(self.out_key) > 1 else self.out_key[0]!r}, "
            f"worker={self.worker_index}/{self.num_workers})"
        )
