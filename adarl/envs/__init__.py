"""Perturbed dynamics for robust RL: per-episode schedules of physical parameters, as a TorchRL transform.

See ``docs/perturbed-dynamics.md``. The package's names load on first use (PEP 562), so that the schedule grammar
(:mod:`adarl.envs.schedules`) and the env registry (:mod:`adarl.envs.registry`), which the recipe schema
validates against, import without TorchRL or MuJoCo.

* :mod:`adarl.envs.schedules` - episode schedules and their grammar (``{kind: sinusoid | uniform | fixed | list}``);
* :mod:`adarl.envs.registry` - env ids, which parameters each env has and their ranges, presets by name, the envs'
  data (:func:`intrinsic_rank`);
* :mod:`adarl.envs.declared` - any gymnasium id, and the parameters a recipe declares on MuJoCo model fields;
* :mod:`adarl.envs.obs_norm` - observation normalisation with TorchRL's ``VecNormV2`` (checkpoint, freeze, export);
* :mod:`adarl.envs.registration` - :func:`register_env` / :func:`register_parameter` for installed packages;
* :mod:`adarl.envs.presets` - the presets' schedules (the paper's, Table 2's boxes, ours);
* :mod:`adarl.envs.mujoco_appliers` - the appliers that put parameter values into a live env (MuJoCo, CartPole);
* :mod:`adarl.envs.perturbation` - :class:`PerturbedDynamicsEnvTransform`, the TorchRL ``Transform``;
* :mod:`adarl.envs.factory` - :func:`make_env` / :func:`make_eval_env`;
* :mod:`adarl.envs.state` - snapshots of live envs mid-episode (exact resume);
* :mod:`adarl.envs.linear_cartpole` - the linear CartPole of paper App. A.1.
"""

from __future__ import annotations

import importlib

# public name -> the module that defines it (imported when the name is first read)
_EXPORTS: dict[str, str] = {
    **dict.fromkeys(["PerturbedDynamicsEnvTransform", "find_gym_env", "EPISODE_KEY"], "adarl.envs.perturbation"),
    **dict.fromkeys(
        [
            "make_env",
            "make_eval_env",
            "resolve_schedule",
            "perturbation_transform",
            "dynamics_state_dict",
            "load_dynamics_state_dict",
        ],
        "adarl.envs.factory",
    ),
    **dict.fromkeys(
        [
            "Schedule",
            "SinusoidSchedule",
            "UniformSchedule",
            "FixedSchedule",
            "ListSchedule",
            "SCHEDULE_KINDS",
            "schedule_from_dict",
            "as_schedule",
            "grid_schedule",
        ],
        "adarl.envs.schedules",
    ),
    **dict.fromkeys(
        [
            "SUPPORTED_ENVS",
            "PAPER_ENVS",
            "MODES",
            "AIR_DENSITY",
            "AIR_VISCOSITY",
            "ACTION_DIMS",
            "ParameterInfo",
            "check_env_id",
            "check_any_env_id",
            "parameters_for",
            "env_parameters",
            "validate_values",
            "validate_schedule",
            "make_schedule",
            "preset_names",
            "quiet_mujoco",
            "supported_envs",
            "action_dim",
            "intrinsic_rank",
        ],
        "adarl.envs.registry",
    ),
    "PRESETS": "adarl.envs.presets",
    **dict.fromkeys(["MODEL_FIELDS", "FieldParameter", "declared_parameters"], "adarl.envs.declared"),
    **dict.fromkeys(
        [
            "make_observation_norm",
            "find_observation_norm",
            "share_observation_norm",
            "obs_norm_state_dict",
            "load_obs_norm_state_dict",
            "ObservationAffine",
            "observation_affine",
        ],
        "adarl.envs.obs_norm",
    ),
    **dict.fromkeys(["register_env", "register_parameter"], "adarl.envs.registration"),
    **dict.fromkeys(
        ["DynamicsApplier", "MujocoDynamics", "CartPoleDynamics", "LinearCartPoleDynamics", "make_applier"],
        "adarl.envs.mujoco_appliers",
    ),
    **dict.fromkeys(
        ["LinearCartPoleEnv", "LINEAR_CARTPOLE_ID", "linear_cartpole_matrices"], "adarl.envs.linear_cartpole"
    ),
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'adarl.envs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later reads skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
