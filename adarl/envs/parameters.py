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

Parameters (lengths are half-lengths, as MuJoCo capsule sizes and the paper's schedules are):

==========================  ============================  =======================================================
env                         parameter                     what changes
==========================  ============================  =======================================================
Hopper-v5, Walker2d-v5      ``torso_length``              torso capsule half-length; the torso's bottom stays put
                                                          (torso body z = 1.05 + T), the thigh(s) hang at -T
Hopper-v5, Walker2d-v5      ``foot_length``               foot capsule half-length (both feet on Walker2d)
Ant-v5, Humanoid-v5         ``gravity``                   ``opt.gravity = [0, 0, -g]``
Ant-v5, Humanoid-v5         ``wind``                      ``opt.wind = [-w, 0, 0]``; turns the air on
                                                          (density 1.2, viscosity 2e-5), without which wind is inert
CartPole-v1                 ``pole_length``               ``length`` (half pole length) and ``polemass_length``
InvertedPendulum-v5         ``pole_length``               pole capsule half-length (the pole scales about the hinge)
every MuJoCo env            ``mass_scale``                every body's mass and inertia times s
every MuJoCo env            ``mass_scale:<body>``         that body's mass and inertia times s
every MuJoCo env            ``friction_scale``            every geom's friction coefficients times s
==========================  ============================  =======================================================

Installed packages add env ids (:func:`register_env`) and parameters (:func:`register_parameter`, e.g. a body's
length on Hopper-v5) through the ``adarl.plugins`` entry-point group, loaded when an id or a parameter name is
not known yet (docs/adding-a-component.md).
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
