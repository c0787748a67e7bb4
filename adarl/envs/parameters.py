"""Which dynamics parameters each environment has, their valid ranges, the presets, and how to apply them: the
public names of four modules, one job each, importable from here as before the split:

* :mod:`adarl.envs.registry` - env ids, parameters and their ranges, presets by name, the envs' data
  (:func:`env_parameters`, :data:`SUPPORTED_ENVS`, :func:`validate_values`, :func:`validate_schedule`,
  :func:`~adarl.envs.registry.intrinsic_rank`); it needs no live environment (nor MuJoCo), so recipes can be
  validated before anything is built;
* :mod:`adarl.envs.registration` - :func:`register_env`, :func:`register_parameter` (installed packages);
* :mod:`adarl.envs.presets` - the presets' schedules (the paper's, its Table 2 boxes, ours);
* :mod:`adarl.envs.mujoco_appliers` - the appliers (:class:`MujocoDynamics`, :class:`CartPoleDynamics`) that edit one
  live gymnasium environment in place, each from a copy of the environment's own compiled defaults, so nothing
  compounds across episodes.

The parameters each env takes, and what each changes, are tabled in :mod:`adarl.envs.registry` (their one home);
plugins add env ids and parameters through :func:`register_env` / :func:`register_parameter`.
"""

from __future__ import annotations

from adarl.envs.mujoco_appliers import (
    CartPoleDynamics,
    DynamicsApplier,
    LinearCartPoleDynamics,
    MujocoDynamics,
    make_applier,
)
from adarl.envs.presets import PRESETS
from adarl.envs.registration import (
    _registry_state,  # noqa: F401 - tests put the registries back with these
    _restore_registry,  # noqa: F401
    register_env,
    register_parameter,
)
from adarl.envs.registry import (
    _MUJOCO_XML,  # noqa: F401 - read by tests
    _PRESET_TABLE,  # noqa: F401
    _SPECIFIC,  # noqa: F401
    AIR_DENSITY,
    AIR_VISCOSITY,
    HOW_TO_REGISTER_ENV,
    MODES,
    PAPER_ENVS,
    SUPPORTED_ENVS,
    ParameterInfo,
    body_parameter,
    check_env_id,
    check_mode,
    default_xml_path,
    env_parameters,
    is_mujoco,
    make_schedule,
    preset_names,
    quiet_mujoco,
    supported_envs,
    validate_schedule,
    validate_values,
)

__all__ = [
    "SUPPORTED_ENVS",
    "PAPER_ENVS",
    "MODES",
    "PRESETS",
    "AIR_DENSITY",
    "AIR_VISCOSITY",
    "ParameterInfo",
    "check_env_id",
    "check_mode",
    "env_parameters",
    "validate_values",
    "validate_schedule",
    "make_schedule",
    "preset_names",
    "DynamicsApplier",
    "MujocoDynamics",
    "CartPoleDynamics",
    "LinearCartPoleDynamics",
    "make_applier",
    "quiet_mujoco",
    "register_env",
    "register_parameter",
    "supported_envs",
    "HOW_TO_REGISTER_ENV",
    "default_xml_path",
    "is_mujoco",
    "body_parameter",
]
