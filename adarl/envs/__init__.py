"""Perturbed dynamics for robust RL: per-episode schedules of physical parameters, as a TorchRL transform.

See ``docs/perturbed-dynamics.md``.
"""

from adarl.envs.factory import (
    dynamics_state_dict,
    load_dynamics_state_dict,
    make_env,
    make_eval_env,
    perturbation_transform,
    resolve_schedule,
)
from adarl.envs.linear_cartpole import LINEAR_CARTPOLE_ID, LinearCartPoleEnv, linear_cartpole_matrices
from adarl.envs.parameters import (
    AIR_DENSITY,
    AIR_VISCOSITY,
    MODES,
    PAPER_ENVS,
    PRESETS,
    SUPPORTED_ENVS,
    CartPoleDynamics,
    DynamicsApplier,
    LinearCartPoleDynamics,
    MujocoDynamics,
    ParameterInfo,
    check_env_id,
    env_parameters,
    make_applier,
    make_schedule,
    preset_names,
    quiet_mujoco,
    validate_schedule,
    validate_values,
)
from adarl.envs.perturbation import EPISODE_KEY, PerturbedDynamicsEnvTransform, find_gym_env
from adarl.envs.schedules import (
    SCHEDULE_KINDS,
    FixedSchedule,
    ListSchedule,
    Schedule,
    SinusoidSchedule,
    UniformSchedule,
    as_schedule,
    grid_schedule,
    schedule_from_dict,
)

__all__ = [
    # transform and factory
    "PerturbedDynamicsEnvTransform",
    "make_env",
    "make_eval_env",
    "resolve_schedule",
    "perturbation_transform",
    "dynamics_state_dict",
    "load_dynamics_state_dict",
    "find_gym_env",
    "EPISODE_KEY",
    # schedules
    "Schedule",
    "SinusoidSchedule",
    "UniformSchedule",
    "FixedSchedule",
    "ListSchedule",
    "SCHEDULE_KINDS",
    "schedule_from_dict",
    "as_schedule",
    "grid_schedule",
    # registry and presets
    "SUPPORTED_ENVS",
    "PAPER_ENVS",
    "MODES",
    "PRESETS",
    "AIR_DENSITY",
    "AIR_VISCOSITY",
    "ParameterInfo",
    "check_env_id",
    "env_parameters",
    "validate_values",
    "validate_schedule",
    "make_schedule",
    "preset_names",
    # appliers
    "DynamicsApplier",
    "MujocoDynamics",
    "CartPoleDynamics",
    "LinearCartPoleDynamics",
    # the linear CartPole of paper App. A.1
    "LinearCartPoleEnv",
    "LINEAR_CARTPOLE_ID",
    "linear_cartpole_matrices",
    "make_applier",
    "quiet_mujoco",
]
