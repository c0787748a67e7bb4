"""Which environments adarl perturbs and which dynamics parameters each has: ids, parameters and their valid
ranges, presets by name, what each registered parameter edits, and the envs' data (action dimensions).

The registry needs no live environment and imports neither MuJoCo nor TorchRL, so recipes are validated before
anything is built. Installed packages add ids and parameters through :mod:`adarl.envs.registration`; the presets'
schedules are :mod:`adarl.envs.presets`, the appliers that edit a live env :mod:`adarl.envs.mujoco_appliers`.

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
not known yet (docs/adding-a-component.md). Any other id in gymnasium's registry is accepted too
(:func:`check_any_env_id`): no presets but ``none``, and the parameters a recipe declares (:mod:`adarl.envs.declared`).

Long because: every lookup of an env id and its parameters answers for adarl's envs, the plugins' and gymnasium's
plain ones in one place (ids, parameters with the declared ones, presets, validation), which the schema, the
appliers and the registration all read.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass
from functools import cache
from importlib.util import find_spec
from typing import Any

import numpy as np

from adarl import plugins
from adarl.envs.declared import FieldParameter, declared_parameters, gymnasium_entry_point, gymnasium_ids
from adarl.envs.presets import PRESETS, generic_presets, paper_env_presets
from adarl.envs.schedules import FixedSchedule, Schedule
from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean

__all__ = [
    "SUPPORTED_ENVS",
    "PAPER_ENVS",
    "MODES",
    "PRESETS",
    "AIR_DENSITY",
    "AIR_VISCOSITY",
    "ACTION_DIMS",
    "ENV_IDS",
    "ParameterInfo",
    "ParameterApply",
    "check_env_id",
    "check_any_env_id",
    "env_provenance",
    "parameters_for",
    "check_mode",
    "is_mujoco",
    "default_xml_path",
    "body_parameter",
    "env_parameters",
    "validate_values",
    "validate_schedule",
    "make_schedule",
    "preset_names",
    "quiet_mujoco",
    "supported_envs",
    "action_dim",
    "intrinsic_rank",
    "HOW_TO_REGISTER_ENV",
]

#: The environments the paper perturbs (each has a ``paper`` preset).
PAPER_ENVS: tuple[str, ...] = (
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "Humanoid-v5",
    "CartPole-v1",
    "InvertedPendulum-v5",
    "LinearCartPole-v0",  # adarl.envs.linear_cartpole: the linear system of paper App. A.1 (Eq. 17)
)

# The gymnasium MuJoCo v5 environments and their default model files (gymnasium/envs/mujoco/assets).
_MUJOCO_XML: dict[str, str] = {
    "Hopper-v5": "hopper.xml",
    "Walker2d-v5": "walker2d_v5.xml",
    "Ant-v5": "ant.xml",
    "Humanoid-v5": "humanoid.xml",
    "InvertedPendulum-v5": "inverted_pendulum.xml",
    "HalfCheetah-v5": "half_cheetah.xml",
    "Swimmer-v5": "swimmer.xml",
    "Reacher-v5": "reacher.xml",
    "Pusher-v5": "pusher_v5.xml",
    "InvertedDoublePendulum-v5": "inverted_double_pendulum.xml",
    "HumanoidStandup-v5": "humanoidstandup.xml",
}

#: adarl's own environment ids (:func:`supported_envs` adds those installed plugins register).
SUPPORTED_ENVS: tuple[str, ...] = PAPER_ENVS + tuple(e for e in _MUJOCO_XML if e not in PAPER_ENVS)

#: Physics modes: ``consistent`` (mass and inertia follow the geometry) and ``ompo`` (geometry only, as OMPO).
MODES: tuple[str, ...] = ("consistent", "ompo")

#: The air OMPO turns on for the wind parameter (MuJoCo's default density 0 makes wind inert).
AIR_DENSITY = 1.2
AIR_VISCOSITY = 2e-5

_INF = math.inf

# ----------------------------------------------------------------------------------------------------------------
# Parameters and env ids
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterInfo:
    """One perturbable parameter: its environment default and the range in which the model stays valid.

    ``low_open`` / ``high_open`` say whether the bound itself is excluded (lengths and scales must be ``> 0``).
    Only ``name`` and ``default`` are required (the range then is every finite number), e.g. a length:
    ``ParameterInfo("thigh_length", 0.225, low=0.0, low_open=True, unit="m", description="thigh half-length")``.
    A physical quantity should state physical bounds, so that an impossible value (``1e308`` m) is refused when a
    recipe is validated rather than deep in MuJoCo: :meth:`within_factor` gives ``[default / f, default * f]``,
    the range adarl's own lengths (``f = 10``) and scales (``f = 100``) have.
    """

    name: str
    default: float
    low: float = -_INF
    high: float = _INF
    low_open: bool = False
    high_open: bool = False
    unit: str = ""
    description: str = ""

    @classmethod
    def within_factor(
        cls, name: str, default: float, factor: float, *, unit: str = "", description: str = ""
    ) -> ParameterInfo:
        """A positive quantity allowed within ``factor`` of its nominal ``default``: ``[default / factor,
        default * factor]``, e.g. ``ParameterInfo.within_factor("thigh_length", 0.225, 10, unit="m")``.

        >>> ParameterInfo.within_factor("torso_length", 0.2, 10, unit="m").allowed()
        'finite numbers >= 0.02 and <= 2'
        """
        if not (math.isfinite(default) and default > 0 and math.isfinite(factor) and factor > 1):
            raise AdaRLValueError(
                f"ParameterInfo.within_factor({name!r}): needs a finite default > 0 and a finite factor > 1, got "
                f"default={default!r}, factor={factor!r}"
            )
        return cls(name, default, default / factor, default * factor, False, False, unit, description)

    def allowed(self) -> str:
        """The valid range in words, e.g. ``'finite numbers > 0'``."""
        parts = []
        if self.low > -_INF:
            parts.append(f"{'>' if self.low_open else '>='} {self.low:g}")
        if self.high < _INF:
            parts.append(f"{'<' if self.high_open else '<='} {self.high:g}")
        return "finite numbers" + (" " + " and ".join(parts) if parts else "")

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def validate(self, value: Any, env_id: str = "", what: str = "") -> float:
        """``value`` as a float, or :class:`AdaRLValueError` naming it and the allowed range."""
        where = f" for {env_id}" if env_id else ""
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise AdaRLValueError(
                f"{what or self.name!s}{where}: expected a number, got {value!r}; allowed: {self.allowed()}"
            )
        value = float(value)
        if not self.contains(value):
            raise AdaRLValueError(
                f"{what or self.name!s}{where}: value {value!r} is outside its allowed range; allowed: "
                f"{self.allowed()}" + (f" (default {self.default:g})" if math.isfinite(self.default) else "")
            )
        return value

    def as_dict(self) -> dict:
        return asdict(self)


# Physical bounds (issue 30.7): a value MuJoCo would choke on (a 1e308 m torso, a 1e-300 mass) is refused when a
# recipe is validated, naming the parameter, the value and the range, instead of ending in a MuJoCo traceback. A
# length stays within LENGTH_FACTOR of its nominal value, a mass or friction scale within SCALE_FACTOR of 1 (the
# paper's widest ranges are within 3x: Hopper's foot 0.195 -> 0.59, Ant's gravity 9.81 -> 19.6).
#: a length parameter's allowed range: ``[nominal / LENGTH_FACTOR, nominal * LENGTH_FACTOR]``
LENGTH_FACTOR = 10.0
#: a scale parameter's allowed range (mass, friction): ``[1 / SCALE_FACTOR, SCALE_FACTOR]``
SCALE_FACTOR = 100.0
#: gravity in ``[0, GRAVITY_FACTOR * 9.81]`` m/s^2 (zero gravity is physical)
GRAVITY_FACTOR = 10.0
#: wind speed within ``[-MAX_WIND, MAX_WIND]`` m/s (a category-5 hurricane is ~70 m/s)
MAX_WIND = 100.0


def _length(name: str, default: float, description: str) -> ParameterInfo:
    return ParameterInfo.within_factor(name, default, LENGTH_FACTOR, unit="m", description=description)


def _scale(name: str, description: str) -> ParameterInfo:
    return ParameterInfo.within_factor(name, 1.0, SCALE_FACTOR, description=description)


_GRAVITY = ParameterInfo(
    "gravity",
    9.81,
    0.0,
    GRAVITY_FACTOR * 9.81,
    False,
    False,
    "m/s^2",
    "gravitational acceleration g: opt.gravity = [0, 0, -g]",
)
_WIND = ParameterInfo(
    "wind",
    0.0,
    -MAX_WIND,
    MAX_WIND,
    False,
    False,
    "m/s",
    f"wind speed w: opt.wind = [-w, 0, 0]; turns the air on (density {AIR_DENSITY}, viscosity {AIR_VISCOSITY})",
)

_SPECIFIC: dict[str, tuple[ParameterInfo, ...]] = {
    "Hopper-v5": (
        _length("torso_length", 0.2, "torso half-length T (torso body z = 1.05 + T, thigh at -T)"),
        _length("foot_length", 0.195, "foot half-length F"),
    ),
    "Walker2d-v5": (
        _length("torso_length", 0.2, "torso half-length T (torso body z = 1.05 + T, both thighs at -T)"),
        _length("foot_length", 0.1, "half-length F of both feet"),
    ),
    "Ant-v5": (_GRAVITY, _WIND),
    "Humanoid-v5": (_GRAVITY, _WIND),
    "CartPole-v1": (_length("pole_length", 0.5, "half pole length l (CartPole's `length`)"),),
    "LinearCartPole-v0": (_length("pole_length", 0.5, "half pole length l of the linear CartPole (Eq. 17)"),),
    "InvertedPendulum-v5": (_length("pole_length", 0.3, "pole half-length (the pole is scaled about its hinge)"),),
}

_GENERIC: tuple[ParameterInfo, ...] = (
    _scale("mass_scale", "every body's mass and inertia times s"),
    _scale("friction_scale", "every geom's friction coefficients (sliding, torsional, rolling) times s"),
)

_BODY_MASS_PREFIX = "mass_scale:"

HOW_TO_REGISTER_ENV = (
    "register one with adarl.register_env(...) (a parameter: adarl.register_parameter(...)) in a package that "
    f"declares an {plugins.ENTRY_POINT_GROUP!r} entry point, then pip install it (docs/adding-a-component.md)"
)

#: What a registered parameter does: ``apply(editor, value, defaults)``. For a MuJoCo env ``editor`` edits the
#: model's geometry (``set_body_z``, ``set_half_length``, ``scale_along``; an ``MjSpec`` in ``consistent`` mode,
#: the live arrays in ``ompo`` mode); for another registered env it is the live (unwrapped) gymnasium env.
#: ``defaults``: every parameter's default by name (and the built-in edits' own numbers).
ParameterApply = Callable[[Any, float, Mapping[str, Any]], None]


@dataclass(frozen=True)
class _RegisteredEnv:
    env_id: str
    xml: str | None  # its MuJoCo model file (a gymnasium asset name for adarl's own), None for an env without one
    description: str
    provider: str | None  # the distribution whose entry point registered it (None: registered directly, or adarl's)


class _EnvIds(plugins.Registry):
    """The env ids: adarl's own (:data:`SUPPORTED_ENVS`, registered first, through the same registry) and those of
    :func:`~adarl.envs.registration.register_env`. An unknown id of another version of a known env is pointed at
    the supported version."""

    def unknown(self, env_id: Any) -> UnknownNameError:
        known = tuple(self.names(load=False))
        typed = {"kind": self.key, "name": env_id, "allowed": known}
        family = env_id.rsplit("-v", 1)[0].lower()
        for supported in known:
            if supported.rsplit("-v", 1)[0].lower() == family:
                kind = "gymnasium " if supported in SUPPORTED_ENVS else ""
                return UnknownNameError(
                    f"env id {env_id!r} is not supported: the perturbations are written for the {kind}"
                    f"{supported.rsplit('-', 1)[1]} models (their XML bodies and geoms); use {supported!r}. "
                    f"Supported: {list(known)}",
                    **typed,
                )
        return UnknownNameError(
            f"unknown env id {env_id!r}; supported: {list(known)}{did_you_mean(env_id, known)} (no installed plugin "
            f"registers it; {HOW_TO_REGISTER_ENV})",
            **typed,
        )


# Every env id, adarl's own first.
_REGISTERED: dict[str, _RegisteredEnv] = {}
ENV_IDS = _EnvIds(
    "env id",
    what="env",
    how=HOW_TO_REGISTER_ENV,
    order=list,
    entries=_REGISTERED,
    describe=lambda old: f"from {old.provider or 'register_env'}",
    noun="id",
)


def _known_envs() -> tuple[str, ...]:
    return tuple(ENV_IDS.names(load=False))


def supported_envs(*, load: bool = True) -> tuple[str, ...]:
    """Every env id adarl accepts: :data:`SUPPORTED_ENVS` (adarl's own), then those registered with
    :func:`register_env` (``load``: installed plugins' ``adarl.plugins`` entry points are loaded first)."""
    return tuple(ENV_IDS.names(load=load))


def check_env_id(env_id: Any) -> str:
    """``env_id`` if supported, else :class:`~adarl.errors.UnknownNameError` (pointing other versions at the
    supported one).

    An id not known yet gives installed plugins (the ``adarl.plugins`` entry points) a chance to register it."""
    if not isinstance(env_id, str):
        raise AdaRLValueError(f"env id must be a string, got {env_id!r}; supported: {list(_known_envs())}")
    ENV_IDS.get(env_id)
    return env_id


def check_any_env_id(env_id: Any) -> str:
    """``env_id`` if adarl knows it (:func:`check_env_id`, installed plugins loaded) or gymnasium's registry has it
    (a plain gymnasium env: no presets, the parameters a recipe declares); else
    :class:`~adarl.errors.UnknownNameError` with a did-you-mean over both."""
    if not isinstance(env_id, str):
        raise AdaRLValueError(f"env id must be a string, got {env_id!r}; supported: {list(_known_envs())}")
    if env_id in _REGISTERED:
        return env_id
    try:
        return check_env_id(env_id)
    except UnknownNameError:
        gym_ids = gymnasium_ids()
        if env_id in gym_ids:
            return env_id
        known = _known_envs()
        raise UnknownNameError(
            f"unknown env id {env_id!r}: neither adarl nor gymnasium registers it"
            f"{did_you_mean(env_id, (*known, *gym_ids))}; adarl's own (with perturbation presets): {list(known)}; "
            "any id in gymnasium's registry runs too, with env.perturbation.preset: none or parameters declared in "
            f"env.parameters (gymnasium.pprint_registry() lists them; an env of your own: gymnasium.register, or "
            f"{HOW_TO_REGISTER_ENV})",
            kind=ENV_IDS.key,
            name=env_id,
            allowed=known,
        ) from None


def env_provenance(env_id: str) -> dict:
    """Where ``env_id`` came from, for the run folder's plugins.json: adarl or the plugin that registered it, or,
    for a plain gymnasium env, gymnasium's version and the env's entry point."""
    env_id = check_any_env_id(env_id)
    if env_id in _REGISTERED:
        return ENV_IDS.provenance(env_id)
    return {**plugins.provenance("gymnasium"), "entry_point": gymnasium_entry_point(env_id)}


def _declared_info(p: FieldParameter) -> ParameterInfo:
    return ParameterInfo(
        p.name,
        math.nan,  # the model's own value, known once the env is built
        -_INF if p.low is None else p.low,
        _INF if p.high is None else p.high,
        description=f"{p.field}{list(p.index) if p.index else ''} (declared in env.parameters)",
    )


def parameters_for(
    env_id: str, declared: Mapping[str, Any] | None = None, *, require: Iterable[Any] = ()
) -> dict[str, ParameterInfo]:
    """The parameters a recipe's env has: adarl's registered ones (:func:`env_parameters`; none for a plain
    gymnasium env) and those it declares in ``env.parameters`` (``declared``: ``{name: {field, index?, low?,
    high?}}``, :mod:`adarl.envs.declared`). A declared name that the env already has is refused."""
    env_id = check_any_env_id(env_id)
    spec = declared_parameters(declared)
    own = env_parameters(env_id, require=[n for n in require if n not in spec]) if env_id in _REGISTERED else {}
    for name, p in spec.items():
        if name in own:
            raise AdaRLValueError(
                f"env.parameters.{name}: {env_id} already has a parameter named {name!r} ({own[name].description}); "
                "pick another name for the declared one"
            )
        own[name] = _declared_info(p)
    return own


def check_mode(mode: Any) -> str:
    if mode not in MODES:
        raise AdaRLValueError(f"unknown physics mode {mode!r}; allowed modes: {list(MODES)}")
    return mode


def is_mujoco(env_id: str) -> bool:
    """Whether ``env_id`` simulates with MuJoCo (adarl's own MuJoCo ids, and gymnasium's MuJoCo envs)."""
    env_id = check_any_env_id(env_id)
    if env_id in _REGISTERED:
        return env_id in _MUJOCO_XML
    return gymnasium_entry_point(env_id).startswith("gymnasium.envs.mujoco")


def _gymnasium_assets() -> str:
    """gymnasium's MuJoCo asset folder, found without importing gymnasium (nor MuJoCo)."""
    spec = find_spec("gymnasium")
    if spec is None or spec.origin is None:
        raise AdaRLValueError("gymnasium is not installed: its MuJoCo model files cannot be found")
    return os.path.join(os.path.dirname(spec.origin), "envs", "mujoco", "assets")


def default_xml_path(env_id: str) -> str:
    """The MuJoCo model file the env id loads by default (a gymnasium asset, or the file it was registered with)."""
    env_id = check_env_id(env_id)
    if env_id not in _MUJOCO_XML:
        raise AdaRLValueError(f"{env_id} has no MuJoCo model file (it was registered without xml=...)")
    return os.path.join(_gymnasium_assets(), _MUJOCO_XML[env_id])  # an absolute path is kept as it is


@contextlib.contextmanager
def quiet_mujoco() -> Iterator[None]:
    """Route MuJoCo warnings away from ``MUJOCO_LOG.TXT`` and stdout while building models.

    The HalfCheetah XML uses the deprecated ``settotalmass`` attribute, which otherwise makes MuJoCo 4 print a
    warning and write ``MUJOCO_LOG.TXT`` into the working directory. Process-wide while active.
    """
    import mujoco

    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda message: None)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


@cache
def _body_names(env_id: str) -> tuple[str, ...]:
    import mujoco

    with quiet_mujoco():
        model = mujoco.MjModel.from_xml_path(default_xml_path(env_id))
    return tuple(name for name in (model.body(i).name for i in range(1, model.nbody)) if name)


def body_parameter(body: str) -> str:
    """The name of the per-body mass parameter of ``body`` (``mass_scale:<body>``)."""
    return _BODY_MASS_PREFIX + body


def _parameters(env_id: str) -> dict[str, ParameterInfo]:
    params = {p.name: p for p in _SPECIFIC.get(env_id, ())}
    if env_id in _MUJOCO_XML:
        params.update({p.name: p for p in _GENERIC})
        for body in _body_names(env_id):
            name = body_parameter(body)
            params[name] = _scale(name, f"mass and inertia of body {body!r} times s")
    return params


def env_parameters(env_id: str, *, require: Iterable[Any] = ()) -> dict[str, ParameterInfo]:
    """``{name: ParameterInfo}`` for every parameter ``env_id`` accepts (default value and valid range).

    MuJoCo environments also get ``mass_scale``, ``friction_scale`` and one ``mass_scale:<body>`` per named body
    of the default model, and every environment the parameters registered for it (:func:`register_parameter`).
    ``require``: names the caller needs; when one is not known, installed plugins are loaded first.
    """
    env_id = check_env_id(env_id)
    params = _parameters(env_id)
    if any(name not in params for name in require):
        ENV_IDS.load()
        params = _parameters(env_id)
    return params


def _unknown(env_id: str, name: Any, allowed: Mapping) -> AdaRLValueError:
    return AdaRLValueError(
        f"unknown parameter {name!r} for {env_id}; allowed: {list(allowed)}{did_you_mean(str(name), allowed)} "
        "(to add one: declare it in the recipe's env.parameters, or adarl.register_parameter(...) in an installed "
        "plugin, docs/adding-a-component.md)"
    )


def validate_values(
    env_id: str, values: Mapping[str, Any], declared: Mapping[str, Any] | None = None
) -> dict[str, float]:
    """Check names and values against the registry (and the parameters ``declared`` in ``env.parameters``);
    returns ``{name: float}`` in sorted order."""
    if not isinstance(values, Mapping):
        raise AdaRLValueError(f"dynamics values for {env_id} must be a mapping {{parameter: value}}, got {values!r}")
    allowed = parameters_for(env_id, declared, require=values)
    out = {}
    for name in sorted(values, key=str):
        if name not in allowed:
            raise _unknown(env_id, name, allowed)
        out[name] = allowed[name].validate(values[name], env_id)
    return out


def _check_schedule(env_id: str, schedule: Schedule, allowed: Mapping[str, ParameterInfo]) -> Schedule:
    for name in schedule.params:
        if name not in allowed:
            raise _unknown(env_id, name, allowed)
    for name, (lo, hi) in schedule.bounds().items():
        for value in (lo, hi):
            allowed[name].validate(value, env_id, what=f"{name} (the {schedule.kind} schedule reaches {value!r})")
    return schedule


def validate_schedule(env_id: str, schedule: Schedule, declared: Mapping[str, Any] | None = None) -> Schedule:
    """Check that every parameter of ``schedule`` exists for ``env_id`` (or is ``declared`` in ``env.parameters``)
    and every value it can produce is valid."""
    return _check_schedule(env_id, schedule, parameters_for(env_id, declared, require=schedule.params))


# ----------------------------------------------------------------------------------------------------------------
# What adarl's own geometry parameters edit (a registered parameter's apply has the same form)
# ----------------------------------------------------------------------------------------------------------------


def _torso(thighs: tuple[str, ...]):
    def edit(editor, value: float, defaults: Mapping[str, Any]) -> None:
        # Keep the torso's bottom where it is (OMPO: torso z = 1.05 + T with the v5 defaults z=1.25, T=0.2).
        bottom = defaults["torso_z"] - defaults["torso_half"]
        editor.set_body_z("torso", bottom + value)
        for thigh in thighs:
            editor.set_body_z(thigh, -value)
        editor.set_half_length("torso_geom", value)

    return edit


def _feet(geoms: tuple[str, ...]):
    def edit(editor, value: float, defaults: Mapping[str, Any]) -> None:
        for geom in geoms:
            editor.set_half_length(geom, value)

    return edit


def _pole_edit(editor, value: float, defaults: Mapping[str, Any]) -> None:
    editor.scale_along("cpole", value / defaults["pole_length"])


# Geometry parameters per MuJoCo env: name -> edit(editor, value, defaults).
_GEOMETRY: dict[str, dict[str, Any]] = {
    "Hopper-v5": {"torso_length": _torso(("thigh",)), "foot_length": _feet(("foot_geom",))},
    "Walker2d-v5": {
        "torso_length": _torso(("thigh", "thigh_left")),
        "foot_length": _feet(("foot_geom", "foot_left_geom")),
    },
    "InvertedPendulum-v5": {"pole_length": _pole_edit},
}

# Bodies and geoms the geometry edits address by name (they are OMPO's indices in the v5 XMLs).
_REQUIRED_NAMES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "Hopper-v5": (("torso", "thigh"), ("torso_geom", "foot_geom")),
    "Walker2d-v5": (("torso", "thigh", "thigh_left"), ("torso_geom", "foot_geom", "foot_left_geom")),
    "InvertedPendulum-v5": (("pole",), ("cpole",)),
}


# ----------------------------------------------------------------------------------------------------------------
# Presets by name, and adarl's own env ids
# ----------------------------------------------------------------------------------------------------------------

_PRESET_TABLE: dict[str, dict[str, Schedule]] = paper_env_presets()
for _env_id in SUPPORTED_ENVS:  # adarl's own ids, registered as a plugin's are; the generic presets where no paper's
    _PRESET_TABLE.setdefault(_env_id, generic_presets())
    ENV_IDS.register(_env_id, _RegisteredEnv(_env_id, _MUJOCO_XML.get(_env_id), "adarl's own", None))


def preset_names(env_id: str) -> list[str]:
    """The presets available for ``env_id`` (``none`` always is; it is the only one of a plain gymnasium env)."""
    return [*_PRESET_TABLE.get(check_any_env_id(env_id), {}), "none"]


def _written_for(env_id: str) -> str:
    """For a gymnasium id of another version of one of adarl's envs: which one the presets are written for."""
    family = env_id.rsplit("-v", 1)[0].lower()
    same = [k for k in _known_envs() if k.rsplit("-v", 1)[0].lower() == family]
    return (
        f"; the presets are written for the {same[0].rsplit('-', 1)[1]} model (its XML bodies and geoms): use "
        f"{same[0]!r}"
        if same
        else ""
    )


def make_schedule(env_id: str, preset: str = "paper") -> Schedule:
    """The schedule of a named preset for ``env_id`` (a fresh object; ``none`` gives an empty fixed schedule)."""
    available = preset_names(env_id)
    if preset == "none":
        return FixedSchedule({})
    if env_id not in _PRESET_TABLE:
        raise AdaRLValueError(
            f"preset {preset!r} is not available for {env_id!r}, a gymnasium env adarl has no presets for; allowed "
            f"presets: {available} (or a schedule over parameters declared in env.parameters){_written_for(env_id)}"
        )
    if preset not in _PRESET_TABLE[env_id]:
        ENV_IDS.load()  # an installed plugin may register env ids and presets not loaded yet
        available = preset_names(env_id)
    if preset not in _PRESET_TABLE[env_id]:
        hint = " (the paper has no schedule for this env)" if preset == "paper" else ""
        raise AdaRLValueError(f"unknown preset {preset!r} for {env_id}{hint}; allowed presets: {available}")
    return _PRESET_TABLE[env_id][preset].from_dict(_PRESET_TABLE[env_id][preset].to_dict())


# ----------------------------------------------------------------------------------------------------------------
# The envs' data
# ----------------------------------------------------------------------------------------------------------------

#: Action dimension ``d_a`` of the paper's environments (and HalfCheetah): the one place adarl records it.
ACTION_DIMS: dict[str, int] = {
    "Hopper-v5": 3,
    "Walker2d-v5": 6,
    "Ant-v5": 8,
    "Humanoid-v5": 17,
    "HalfCheetah-v5": 6,
    "InvertedPendulum-v5": 1,
    "CartPole-v1": 1,
    "LinearCartPole-v0": 1,
}


def action_dim(env_id: str) -> int | None:
    """The action dimension ``d_a`` of ``env_id`` (:data:`ACTION_DIMS`), None for an env it does not record.

    >>> action_dim("Hopper-v5"), action_dim("Pong-v5")
    (3, None)
    """
    return ACTION_DIMS.get(env_id)


def intrinsic_rank(env_id: str) -> int | None:
    """``2 * d_a + 1``, the intrinsic rank of Tiwari et al. (2025) that the paper's Fig. 4 draws, for a known env;
    None otherwise.

    >>> intrinsic_rank("Hopper-v5"), intrinsic_rank("Pong-v5")
    (7, None)
    """
    d = action_dim(env_id)
    return None if d is None else 2 * d + 1
