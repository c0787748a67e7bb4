"""``make_env`` / ``make_eval_env``: a TorchRL env with per-episode perturbed dynamics, ready for a collector.

Layout (``num_envs == 1``)::

    TransformedEnv(GymEnv(env_id), Compose(PerturbedDynamicsEnvTransform, DoubleToFloat, StepCounter, RewardSum))

and for ``num_envs > 1`` the perturbation lives inside each worker::

    TransformedEnv(SerialEnv|ParallelEnv([TransformedEnv(GymEnv, PerturbedDynamicsEnvTransform)] * n),
                   Compose(DoubleToFloat, StepCounter, RewardSum))

``RewardSum`` writes ``"episode_reward"``; the drawn dynamics are under ``(dynamics_key, <param>)``. With
``normalize_observations=True`` TorchRL's ``VecNormV2`` on ``"observation"`` comes last
(:mod:`adarl.envs.obs_norm`). ``env_id`` may be any id in gymnasium's registry: without adarl's presets, its
schedule sets the parameters declared in ``parameters`` (:mod:`adarl.envs.declared`).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

from torchrl.envs import Compose, DoubleToFloat, EnvBase, ParallelEnv, RewardSum, SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase
from torchrl.envs.libs.gym import GymEnv

from adarl.envs.declared import declared_dict
from adarl.envs.linear_cartpole import LINEAR_CARTPOLE_ID, LinearCartPoleEnv
from adarl.envs.obs_norm import make_observation_norm
from adarl.envs.perturbation import PerturbedDynamicsEnvTransform
from adarl.envs.presets import PRESETS
from adarl.envs.registry import (
    check_any_env_id,
    check_mode,
    make_schedule,
    preset_names,
    quiet_mujoco,
    validate_values,
)
from adarl.envs.schedules import FixedSchedule, Schedule, as_schedule
from adarl.errors import AdaRLValueError

__all__ = [
    "make_env",
    "make_eval_env",
    "resolve_schedule",
    "perturbation_transform",
    "dynamics_state_dict",
    "load_dynamics_state_dict",
]


def resolve_schedule(
    env_id: str, preset: str | None = "paper", schedule: Schedule | Mapping | str | None = None
) -> Schedule | None:
    """The schedule ``make_env`` would use: ``schedule`` (object, dict or preset name) if given, else the preset's.

    Returns None for plain dynamics (preset ``"none"``).
    """
    env_id = check_any_env_id(env_id)
    if isinstance(schedule, str):  # a preset name given as the schedule
        preset, schedule = schedule, None
    if schedule is not None:
        return as_schedule(schedule)
    if preset is None or preset == "none":
        return None
    if not isinstance(preset, str):
        raise AdaRLValueError(f"preset must be a string; allowed presets for {env_id}: {preset_names(env_id)}")
    return make_schedule(env_id, preset)


def _worker_parts(
    env_id: str,
    schedule: dict | None,
    mode: str,
    dynamics_key: str | tuple[str, ...],
    device: Any,
    max_episode_steps: int | None,
    worker_index: int,
    num_workers: int,
    parameters: dict | None = None,
) -> tuple[EnvBase, PerturbedDynamicsEnvTransform | None]:
    kwargs = {"max_episode_steps": max_episode_steps} if max_episode_steps is not None else {}
    check_any_env_id(env_id)  # in a fresh worker process: an installed plugin registers its env id with gymnasium
    if env_id == LINEAR_CARTPOLE_ID:  # adarl's own TorchRL env, no gymnasium underneath
        base = LinearCartPoleEnv(device=device, **kwargs)
    else:
        with quiet_mujoco():  # HalfCheetah's XML would otherwise write MUJOCO_LOG.TXT
            base = GymEnv(env_id, device=device, **kwargs)
    if schedule is None:
        return base, None
    transform = PerturbedDynamicsEnvTransform(
        env_id,
        schedule,
        mode=mode,
        out_key=dynamics_key,
        worker_index=worker_index,
        num_workers=num_workers,
        parameters=parameters,
    )
    return base, transform


def _worker_env(*args: Any, **kwargs: Any) -> EnvBase:
    """One worker: GymEnv (+ the perturbation). Module-level and picklable, for ParallelEnv's workers."""
    base, transform = _worker_parts(*args, **kwargs)
    return base if transform is None else TransformedEnv(base, transform)


def make_env(
    env_id: str,
    *,
    preset: str | None = "paper",
    schedule: Schedule | Mapping | str | None = None,
    mode: str = "consistent",
    num_envs: int = 1,
    parallel: bool = False,
    seed: int | None = None,
    dynamics_key: str | tuple[str, ...] = "dynamics",
    device: Any = "cpu",
    max_episode_steps: int | None = None,
    perturb: bool = True,
    parameters: Mapping[str, Any] | None = None,
    normalize_observations: bool = False,
) -> TransformedEnv:
    """A TorchRL env whose dynamics change every episode.

    Args:
        env_id: a gymnasium id from :data:`adarl.envs.SUPPORTED_ENVS` (e.g. ``"Hopper-v5"``), one registered
            with :func:`adarl.register_env`, or any other id in gymnasium's registry (presets: ``"none"`` only).
        preset: ``"paper"``, ``"low"``, ``"high"``, ``"nominal"`` or ``"none"`` (see :func:`make_schedule`).
        schedule: a :class:`Schedule` or its dict; overrides ``preset``.
        mode: ``"consistent"`` (mass/inertia follow geometry) or ``"ompo"`` (geometry only, as the paper).
        num_envs: workers; > 1 builds a ``SerialEnv`` (or ``ParallelEnv`` with ``parallel=True``).
        seed: passed to ``env.set_seed`` (each worker gets its own seed, hence its own dynamics stream).
        dynamics_key: output key of the drawn values.
        device: the env's device.
        max_episode_steps: overrides gymnasium's time limit.
        perturb: False for plain dynamics (same as ``preset="none"``).
        parameters: parameters declared on MuJoCo model fields, ``{name: {field, index?, low?, high?}}`` (a
            recipe's ``env.parameters``), which ``schedule`` may set.
        normalize_observations: TorchRL's ``VecNormV2`` on ``"observation"``, last (:mod:`adarl.envs.obs_norm`).

    >>> env = make_env("Hopper-v5", preset="paper", seed=0)
    >>> sorted(env.rollout(3)["next", "dynamics"].keys())  # the dynamics each step ran under
    ['episode', 'foot_length', 'torso_length']
    >>> env.close()
    """
    env_id = check_any_env_id(env_id)
    mode = check_mode(mode)
    declared = declared_dict(parameters)
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise AdaRLValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
    if max_episode_steps is not None and (
        isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1
    ):
        raise AdaRLValueError(f"max_episode_steps must be None or an integer >= 1, got {max_episode_steps!r}")
    if preset is not None and preset not in PRESETS:
        raise AdaRLValueError(f"unknown preset {preset!r} for {env_id}; allowed presets: {preset_names(env_id)}")
    sched = resolve_schedule(env_id, preset, schedule) if perturb else None
    if sched is not None:
        # Validate here (in the main process) rather than inside a worker.
        PerturbedDynamicsEnvTransform(env_id, sched, mode=mode, out_key=dynamics_key, parameters=declared)
    sched_dict = sched.to_dict() if sched is not None else None

    args = (env_id, sched_dict, mode, dynamics_key, device, max_episode_steps)
    common = [DoubleToFloat(), StepCounter(), RewardSum()]
    if normalize_observations:
        common.append(make_observation_norm())
    if num_envs == 1:
        base, transform = _worker_parts(*args, 0, 1, declared)
        env = TransformedEnv(base, Compose(*([transform] if transform is not None else []), *common))
        if transform is not None and declared:
            transform.applier  # noqa: B018 - declared fields are resolved against the model now, not at a reset
    else:
        factories = [functools.partial(_worker_env, *args, w, num_envs, parameters=declared) for w in range(num_envs)]
        cls = ParallelEnv if parallel else SerialEnv
        env = TransformedEnv(cls(num_envs, factories, device=device), Compose(*common))
    if seed is not None:
        env.set_seed(seed)
    return env


def make_eval_env(
    env_id: str,
    schedule_or_preset: Schedule | Mapping | str = "paper",
    *,
    values: Mapping[str, float] | None = None,
    **kwargs: Any,
) -> TransformedEnv:
    """An env with the dynamics fixed at the schedule's :meth:`~Schedule.nominal` (the paper's evaluation).

    ``schedule_or_preset`` is a preset name, a :class:`Schedule`, a schedule dict (``{"kind": ...}``) or a plain
    ``{param: value}`` dict; ``values`` (for sweeps) overrides it. ``"none"`` gives the plain environment.
    Other keyword arguments go to :func:`make_env` (``parameters``: the declared parameters ``values`` may set).
    """
    env_id = check_any_env_id(env_id)
    for key in ("preset", "schedule", "perturb"):
        if key in kwargs:
            raise AdaRLValueError(f"make_eval_env: {key!r} is not accepted; pass schedule_or_preset or values")
    if values is None:
        if isinstance(schedule_or_preset, str):
            sched = resolve_schedule(env_id, schedule_or_preset)
            if sched is None:
                return make_env(env_id, perturb=False, **kwargs)
            values = sched.nominal()
        elif isinstance(schedule_or_preset, Schedule) or (
            isinstance(schedule_or_preset, Mapping) and "kind" in schedule_or_preset
        ):
            values = as_schedule(schedule_or_preset).nominal()
        elif isinstance(schedule_or_preset, Mapping):
            values = dict(schedule_or_preset)
        else:
            raise AdaRLValueError(
                f"make_eval_env: expected a preset name {preset_names(env_id)}, a Schedule, a schedule dict or a "
                f"{{parameter: value}} dict, got {schedule_or_preset!r}"
            )
    values = validate_values(env_id, values, kwargs.get("parameters"))
    return make_env(env_id, schedule=FixedSchedule(values), **kwargs)


def _own_perturbation(env: TransformedEnv) -> PerturbedDynamicsEnvTransform | None:
    transforms = env.transform if isinstance(env.transform, Compose) else [env.transform]
    return next((t for t in transforms if isinstance(t, PerturbedDynamicsEnvTransform)), None)


def perturbation_transform(env: EnvBase) -> PerturbedDynamicsEnvTransform | None:
    """The perturbation transform of an unbatched env (None if it has none or is batched)."""
    while isinstance(env, TransformedEnv):
        found = _own_perturbation(env)
        if found is not None:
            return found
        env = env.base_env
    return None


def _base(env: EnvBase) -> EnvBase:
    """The TransformedEnv holding the perturbation, else the innermost base env (e.g. a SerialEnv)."""
    while isinstance(env, TransformedEnv):
        if _own_perturbation(env) is not None:
            return env
        env = env.base_env
    return env


def dynamics_state_dict(env: EnvBase) -> dict[str, dict]:
    """``{"worker<i>": transform state}`` for every worker of a ``make_env`` env (episode index and RNG state).

    Plain Python types; save it with the run's checkpoint and give it to :func:`load_dynamics_state_dict`.
    """
    base = _base(env)
    if isinstance(base, BatchedEnvBase):
        return {k: dict(v) for k, v in base.state_dict().items()}
    transform = perturbation_transform(env)
    return {} if transform is None else {"worker0": dict(transform.state_dict())}


def load_dynamics_state_dict(env: EnvBase, state: Mapping[str, Mapping]) -> None:
    """Restore what :func:`dynamics_state_dict` saved (same number of workers)."""
    base = _base(env)
    expected = base.num_workers if isinstance(base, BatchedEnvBase) else (1 if perturbation_transform(env) else 0)
    if len(state) != expected:
        raise AdaRLValueError(f"dynamics state has {len(state)} worker(s) {sorted(state)}, the env has {expected}")
    if isinstance(base, BatchedEnvBase):
        base.load_state_dict({k: dict(v) for k, v in state.items()})
    elif expected:
        perturbation_transform(env).load_state_dict(dict(state["worker0"]))
