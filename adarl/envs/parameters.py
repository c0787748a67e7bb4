"""Which dynamics parameters each environment has, their valid ranges, the presets, and how to apply them.

The registry (:func:`env_parameters`, :data:`SUPPORTED_ENVS`, :func:`validate_values`, :func:`validate_schedule`)
needs no live environment, so recipes can be validated before anything is built. The appliers
(:class:`MujocoDynamics`, :class:`CartPoleDynamics`) edit one live gymnasium environment in place; they keep a copy
of the environment's own compiled defaults and start every application from it, so nothing compounds across
episodes.

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

import contextlib
import math
import os
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass
from functools import cache
from importlib.util import find_spec
from typing import Any

import numpy as np

from adarl import plugins
from adarl.envs.schedules import FixedSchedule, Schedule, SinusoidSchedule, UniformSchedule, as_schedule
from adarl.errors import AdaRLValueError, did_you_mean

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

#: Preset names accepted by :func:`make_schedule` (``none``: no perturbation).
PRESETS: tuple[str, ...] = ("paper", "low", "high", "nominal", "none")

#: The air OMPO turns on for the wind parameter (MuJoCo's default density 0 makes wind inert).
AIR_DENSITY = 1.2
AIR_VISCOSITY = 2e-5

_INF = math.inf


# ----------------------------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ParameterInfo:
    """One perturbable parameter: its environment default and the range in which the model stays valid.

    ``low_open`` / ``high_open`` say whether the bound itself is excluded (lengths and scales must be ``> 0``).
    Only ``name`` and ``default`` are required (the range then is every finite number), e.g. a length:
    ``ParameterInfo("thigh_length", 0.225, low=0.0, low_open=True, unit="m", description="thigh half-length")``.
    """

    name: str
    default: float
    low: float = -_INF
    high: float = _INF
    low_open: bool = False
    high_open: bool = False
    unit: str = ""
    description: str = ""

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
                f"{what or self.name!s}{where}: value {value!r} breaks the model; allowed: {self.allowed()} "
                f"(default {self.default:g})"
            )
        return value

    def as_dict(self) -> dict:
        return asdict(self)


def _length(name: str, default: float, description: str) -> ParameterInfo:
    return ParameterInfo(name, default, 0.0, _INF, True, False, "m", description)


def _scale(name: str, description: str) -> ParameterInfo:
    return ParameterInfo(name, 1.0, 0.0, _INF, True, False, "", description)


_GRAVITY = ParameterInfo(
    "gravity", 9.81, 0.0, _INF, False, False, "m/s^2", "gravitational acceleration g: opt.gravity = [0, 0, -g]"
)
_WIND = ParameterInfo(
    "wind",
    0.0,
    -_INF,
    _INF,
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
    xml: str | None  # the absolute path of its MuJoCo model file, None for an env without one
    description: str
    provider: str | None  # the distribution whose entry point registered it (None: registered directly)


# Env ids registered by plugins (adarl's own are SUPPORTED_ENVS), the parameters registered on any env (by
# whom), and the registered envs whose 'nominal' preset follows their parameters' defaults.
_REGISTERED: dict[str, _RegisteredEnv] = {}
_PARAMETER_PROVIDERS: dict[tuple[str, str], str] = {}
_DERIVED_NOMINAL: set[str] = set()
# Built-in envs with an applier of their own (no MuJoCo model to edit): registered parameters would never apply.
_OWN_APPLIER = ("CartPole-v1", "LinearCartPole-v0")
# Parameters MujocoDynamics applies itself (by name, whatever the env): a registered one would be applied twice.
_RESERVED = ("mass_scale", "friction_scale", "gravity", "wind", "episode")


def _known_envs() -> tuple[str, ...]:
    return SUPPORTED_ENVS + tuple(e for e in _REGISTERED if e not in SUPPORTED_ENVS)


def supported_envs(*, load: bool = True) -> tuple[str, ...]:
    """Every env id adarl accepts: :data:`SUPPORTED_ENVS` (adarl's own), then those registered with
    :func:`register_env` (``load``: installed plugins' ``adarl.plugins`` entry points are loaded first)."""
    if load:
        plugins.load_entry_points()
    return _known_envs()


def check_env_id(env_id: Any) -> str:
    """``env_id`` if supported, else :class:`AdaRLValueError` (pointing other versions at the supported one).

    An id not known yet gives installed plugins (the ``adarl.plugins`` entry points) a chance to register it."""
    if not isinstance(env_id, str):
        raise AdaRLValueError(f"env id must be a string, got {env_id!r}; supported: {list(_known_envs())}")
    if env_id in SUPPORTED_ENVS or env_id in _REGISTERED:
        return env_id
    plugins.load_entry_points()
    if env_id in _REGISTERED:
        return env_id
    known = _known_envs()
    family = env_id.rsplit("-v", 1)[0].lower()
    for supported in known:
        if supported.rsplit("-v", 1)[0].lower() == family:
            kind = "gymnasium " if supported in SUPPORTED_ENVS else ""
            raise AdaRLValueError(
                f"env id {env_id!r} is not supported: the perturbations are written for the {kind}"
                f"{supported.rsplit('-', 1)[1]} models (their XML bodies and geoms); use {supported!r}. "
                f"Supported: {list(known)}"
            )
    raise AdaRLValueError(
        f"unknown env id {env_id!r}; supported: {list(known)}{did_you_mean(env_id, known)} (no installed plugin "
        f"registers it; {HOW_TO_REGISTER_ENV})"
    )


def check_mode(mode: Any) -> str:
    if mode not in MODES:
        raise AdaRLValueError(f"unknown physics mode {mode!r}; allowed modes: {list(MODES)}")
    return mode


def is_mujoco(env_id: str) -> bool:
    return check_env_id(env_id) in _MUJOCO_XML


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
        plugins.load_entry_points()
        params = _parameters(env_id)
    return params


def _unknown(env_id: str, name: Any, allowed: Mapping) -> AdaRLValueError:
    return AdaRLValueError(
        f"unknown parameter {name!r} for {env_id}; allowed: {list(allowed)}{did_you_mean(str(name), allowed)} "
        "(to add one: adarl.register_parameter(...) in an installed plugin, docs/adding-a-component.md)"
    )


def validate_values(env_id: str, values: Mapping[str, Any]) -> dict[str, float]:
    """Check names and values against the registry; returns ``{name: float}`` in sorted order."""
    if not isinstance(values, Mapping):
        raise AdaRLValueError(f"dynamics values for {env_id} must be a mapping {{parameter: value}}, got {values!r}")
    allowed = env_parameters(env_id, require=values)
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


def validate_schedule(env_id: str, schedule: Schedule) -> Schedule:
    """Check that every parameter of ``schedule`` exists for ``env_id`` and every value it can produce is valid."""
    return _check_schedule(env_id, schedule, env_parameters(env_id, require=schedule.params))


# ----------------------------------------------------------------------------------------------------------------
# Registration (by installed plugins, through the adarl.plugins entry-point group)
# ----------------------------------------------------------------------------------------------------------------


def _resolve_xml(env_id: str, xml: Any) -> str:
    """The absolute path of a model file given as a path or as the name of a gymnasium asset (``hopper.xml``)."""
    if not isinstance(xml, (str, os.PathLike)) or not str(xml):
        raise AdaRLValueError(f"register_env({env_id!r}): xml must be a path or a gymnasium asset name, got {xml!r}")
    path = os.fspath(xml)
    if not os.path.isabs(path):
        path = os.path.join(_gymnasium_assets(), path)
    if not os.path.isfile(path):
        raise AdaRLValueError(
            f"register_env({env_id!r}): no MuJoCo model file {os.fspath(xml)!r} (looked at {path}); give an "
            "absolute path (e.g. one next to your module) or the name of a gymnasium asset such as 'hopper.xml'"
        )
    return path


def _registry_state() -> dict[str, Any]:
    """A copy of every registry :func:`register_env` and :func:`register_parameter` change (for a rollback)."""
    return {
        "_MUJOCO_XML": dict(_MUJOCO_XML),
        "_SPECIFIC": dict(_SPECIFIC),
        "_GEOMETRY": {k: dict(v) for k, v in _GEOMETRY.items()},
        "_PRESET_TABLE": {k: dict(v) for k, v in _PRESET_TABLE.items()},
        "_REGISTERED": dict(_REGISTERED),
        "_PARAMETER_PROVIDERS": dict(_PARAMETER_PROVIDERS),
        "_DERIVED_NOMINAL": set(_DERIVED_NOMINAL),
    }


def _restore_registry(state: Mapping[str, Any]) -> None:
    """Put the registries back as :func:`_registry_state` saw them (the same objects, refilled)."""
    for name, saved in state.items():
        registry = globals()[name]
        registry.clear()
        registry.update(saved)
    _body_names.cache_clear()


def _provider() -> str | None:
    # the distribution whose entry point is loading now, if any (adarl.plugins' bookkeeping)
    return getattr(plugins, "_current_provider", [None])[0]


def _derive_nominal(env_id: str) -> None:
    """The 'nominal' preset of a registered env that gave none: its own parameters at their defaults (a MuJoCo
    env with none of its own: mass_scale and friction_scale at 1, as the other MuJoCo envs)."""
    own = {p.name: p.default for p in _SPECIFIC.get(env_id, ())}
    if not own and env_id in _MUJOCO_XML:
        own = {"mass_scale": 1.0, "friction_scale": 1.0}
    _PRESET_TABLE[env_id]["nominal"] = FixedSchedule(own)


def register_parameter(env_id: str, info: ParameterInfo, apply: ParameterApply, *, replace: bool = False) -> None:
    """Make ``info.name`` a perturbable parameter of ``env_id`` (adarl's own env or one from :func:`register_env`).

    ``apply(editor, value, defaults)`` sets the parameter to ``value`` (absolutely: every application starts from
    the env's defaults, so nothing compounds). For a MuJoCo env ``editor`` is the geometry editor the built-in
    length parameters use (``set_body_z(body, z)``, ``set_half_length(geom, h)``, ``scale_along(geom, factor)``):
    in ``consistent`` mode it edits an ``MjSpec`` of the model file, which is compiled (cached per value set) so
    that mass and inertia follow the geometry; in ``ompo`` mode it edits the live model's arrays. For a registered
    env without a MuJoCo model ``editor`` is the live (unwrapped) gymnasium env. ``defaults`` maps every parameter
    of the env to its default. Values outside ``info``'s range are refused before ``apply`` is called.

    A name registered twice for the same env is an error (``replace=True`` to override on purpose, a built-in
    length parameter included); ``mass_scale``, ``friction_scale``, ``mass_scale:<body>``, ``gravity``, ``wind``
    and ``episode`` are applied by adarl itself and cannot be registered.
    """
    if env_id in _OWN_APPLIER:
        raise AdaRLValueError(
            f"register_parameter({env_id!r}, ...): {env_id} has an applier of its own, not a MuJoCo model; "
            "register parameters for MuJoCo envs or for envs registered with register_env"
        )
    env_id = check_env_id(env_id)
    if not isinstance(info, ParameterInfo):
        raise AdaRLValueError(
            f"register_parameter({env_id!r}, ...): info must be an adarl.envs.ParameterInfo, got {info!r}"
        )
    name = info.name
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(
            f"register_parameter({env_id!r}, ...): the parameter name must be an identifier (letters, digits, _), "
            f"got {name!r}"
        )
    if name in _RESERVED or name.startswith(_BODY_MASS_PREFIX):
        raise AdaRLValueError(
            f"register_parameter({env_id!r}, ...): {name!r} is applied by adarl itself; reserved names: "
            f"{list(_RESERVED)} and '{_BODY_MASS_PREFIX}<body>'"
        )
    if not callable(apply):
        raise AdaRLValueError(
            f"register_parameter({env_id!r}, {name!r}): apply must be a function apply(editor, value, defaults), "
            f"got {apply!r}"
        )
    info.validate(info.default, env_id, what=f"the default of {name}")
    if any(p.name == name for p in _SPECIFIC.get(env_id, ())) and not replace:
        owner = _PARAMETER_PROVIDERS.get((env_id, name), "adarl")
        raise AdaRLValueError(
            f"parameter {name!r} of {env_id} is already registered (from {owner}); pick another name or pass "
            "replace=True"
        )
    _SPECIFIC[env_id] = (*(p for p in _SPECIFIC.get(env_id, ()) if p.name != name), info)
    _GEOMETRY.setdefault(env_id, {})[name] = apply
    _PARAMETER_PROVIDERS[(env_id, name)] = _provider() or "register_parameter"
    if env_id in _DERIVED_NOMINAL:
        _derive_nominal(env_id)


def register_env(
    env_id: str,
    *,
    xml: str | os.PathLike | None = None,
    parameters: Iterable[tuple[ParameterInfo, ParameterApply]] = (),
    presets: Mapping[str, Schedule | Mapping] | None = None,
    description: str = "",
    replace: bool = False,
) -> None:
    """Make the gymnasium env id ``env_id`` (registered with ``gymnasium.register`` by the plugin itself)
    acceptable to adarl: in recipes (``env.id``), :func:`~adarl.envs.make_env` and the perturbation transform.

    Args:
        xml: its MuJoCo model file (an absolute path, or a gymnasium asset name such as ``"hopper.xml"``) when it
            is a MuJoCo env: it then gets ``mass_scale``, ``friction_scale`` and ``mass_scale:<body>``, and its
            parameters edit that model. Leave it None for an env without MuJoCo.
        parameters: ``(ParameterInfo, apply)`` pairs, each as :func:`register_parameter` takes them.
        presets: named schedules (a :class:`Schedule` or its dict) among ``"paper"``, ``"low"``, ``"high"`` and
            ``"nominal"``; ``"none"`` (plain dynamics) always exists. Without ``"nominal"``, it is every
            parameter of the env at its default. Without ``presets``, a MuJoCo env also gets the generic ``low``
            and ``high`` boxes (mass and friction scales in [0.9, 1.1] and [0.7, 1.3]).
        description: one line, for listings.
        replace: re-register an id registered before (adarl's own ids cannot be replaced).
    """
    if not isinstance(env_id, str) or not env_id or env_id != env_id.strip():
        raise AdaRLValueError(f"register_env: the env id must be a non-empty string without spaces, got {env_id!r}")
    if env_id in SUPPORTED_ENVS:
        raise AdaRLValueError(
            f"register_env({env_id!r}): {env_id} is one of adarl's own envs; add parameters to it with "
            "register_parameter instead"
        )
    old = _REGISTERED.get(env_id)
    if old is not None and not replace:
        raise AdaRLValueError(
            f"env {env_id!r} is already registered (from {old.provider or 'register_env'}); pick another id or "
            "pass replace=True"
        )
    path = None if xml is None else _resolve_xml(env_id, xml)
    pairs = list(parameters)
    for pair in pairs:
        if not (isinstance(pair, tuple) and len(pair) == 2):
            raise AdaRLValueError(
                f"register_env({env_id!r}): parameters must be (ParameterInfo, apply) pairs, got {pair!r}"
            )
    named = dict(presets or {})
    wrong = [p for p in named if p not in PRESETS or p == "none"]
    if wrong:
        raise AdaRLValueError(
            f"register_env({env_id!r}): unknown preset name(s) {wrong}; allowed: "
            f"{[p for p in PRESETS if p != 'none']} ('none' always exists)"
        )
    saved = _registry_state()
    try:
        for key in [k for k in _PARAMETER_PROVIDERS if k[0] == env_id]:
            del _PARAMETER_PROVIDERS[key]
        _DERIVED_NOMINAL.discard(env_id)
        _MUJOCO_XML.pop(env_id, None)
        if path is not None:
            _MUJOCO_XML[env_id] = path
        _body_names.cache_clear()
        _SPECIFIC[env_id] = ()
        _GEOMETRY[env_id] = {}
        _REGISTERED[env_id] = _RegisteredEnv(env_id, path, str(description), _provider())
        _PRESET_TABLE[env_id] = {}
        for info, apply in pairs:
            register_parameter(env_id, info, apply)
        if presets is None and path is not None:
            _PRESET_TABLE[env_id].update({k: v for k, v in _generic_presets().items() if k != "nominal"})
        allowed = _parameters(env_id)
        for name, schedule in named.items():
            try:
                _PRESET_TABLE[env_id][name] = _check_schedule(env_id, as_schedule(schedule), allowed)
            except (AdaRLValueError, TypeError, ValueError) as err:
                raise AdaRLValueError(f"register_env({env_id!r}): preset {name!r}: {err}") from err
        if "nominal" not in _PRESET_TABLE[env_id]:
            _DERIVED_NOMINAL.add(env_id)
            _derive_nominal(env_id)
    except BaseException:
        _restore_registry(saved)
        raise


# ----------------------------------------------------------------------------------------------------------------
# Presets
# ----------------------------------------------------------------------------------------------------------------


def _box(center: Mapping[str, float], half_width: Mapping[str, float]) -> UniformSchedule:
    return UniformSchedule(
        {p: center[p] - half_width[p] for p in center}, {p: center[p] + half_width[p] for p in center}
    )


def _paper_and_boxes(paper: SinusoidSchedule, low_frac: float = 0.5) -> dict[str, Schedule]:
    """Our low/high for the sinusoid envs without a Table 2 box: centre +- half / all of the paper's amplitude."""
    c, a = paper.center, {p: abs(v) for p, v in paper.amplitude.items()}
    return {
        "paper": paper,
        "low": _box(c, {p: low_frac * a[p] for p in c}),
        "high": _box(c, a),
        "nominal": FixedSchedule(c),
    }


def _pole(l0: float) -> dict[str, Schedule]:
    def box(frac: float) -> UniformSchedule:
        return UniformSchedule({"pole_length": (1 - frac) * l0}, {"pole_length": (1 + frac) * l0})

    # paper A.1: l in [0.95 l0, 1.05 l0]; ours: low +-2.5 %, high +-10 %.
    return {"paper": box(0.05), "low": box(0.025), "high": box(0.10), "nominal": FixedSchedule({"pole_length": l0})}


def _generic_presets() -> dict[str, Schedule]:
    # Ours (no paper schedule): RRLS-style mass / friction boxes.
    return {
        "low": UniformSchedule({"mass_scale": 0.9, "friction_scale": 0.9}, {"mass_scale": 1.1, "friction_scale": 1.1}),
        "high": UniformSchedule({"mass_scale": 0.7, "friction_scale": 0.7}, {"mass_scale": 1.3, "friction_scale": 1.3}),
        "nominal": FixedSchedule({"mass_scale": 1.0, "friction_scale": 1.0}),
    }


def _presets() -> dict[str, dict[str, Schedule]]:
    hopper_paper = SinusoidSchedule(
        {"torso_length": 0.4, "foot_length": 0.39}, {"torso_length": 0.2, "foot_length": 0.2}, 0.2
    )
    walker_paper = SinusoidSchedule(
        {"torso_length": 0.2, "foot_length": 0.1}, {"torso_length": 0.1, "foot_length": 0.05}, 0.3
    )
    out: dict[str, dict[str, Schedule]] = {
        "Hopper-v5": {
            "paper": hopper_paper,
            # paper Table 2
            "low": UniformSchedule(
                {"torso_length": 0.31, "foot_length": 0.305}, {"torso_length": 0.49, "foot_length": 0.485}
            ),
            "high": UniformSchedule(
                {"torso_length": 0.25, "foot_length": 0.245}, {"torso_length": 0.55, "foot_length": 0.545}
            ),
            "nominal": FixedSchedule(hopper_paper.nominal()),
        },
        "Walker2d-v5": {
            "paper": walker_paper,
            # paper Table 2
            "low": UniformSchedule(
                {"torso_length": 0.1, "foot_length": 0.05}, {"torso_length": 0.3, "foot_length": 0.15}
            ),
            "high": UniformSchedule(
                {"torso_length": 0.06, "foot_length": 0.03}, {"torso_length": 0.34, "foot_length": 0.17}
            ),
            "nominal": FixedSchedule(walker_paper.nominal()),
        },
        "Ant-v5": _paper_and_boxes(
            SinusoidSchedule({"gravity": 14.715, "wind": 1.0}, {"gravity": 4.905, "wind": 0.2}, 0.5)
        ),
        "Humanoid-v5": _paper_and_boxes(
            SinusoidSchedule({"gravity": 14.715, "wind": 1.0}, {"gravity": 4.905, "wind": 0.5}, 0.5)
        ),
        "CartPole-v1": _pole(0.5),
        "LinearCartPole-v0": _pole(0.5),
        "InvertedPendulum-v5": _pole(0.3),
    }
    for env_id in SUPPORTED_ENVS:
        out.setdefault(env_id, _generic_presets())
    return out


_PRESET_TABLE = _presets()


def preset_names(env_id: str) -> list[str]:
    """The presets available for ``env_id`` (``none`` always is)."""
    return [*_PRESET_TABLE[check_env_id(env_id)], "none"]


def make_schedule(env_id: str, preset: str = "paper") -> Schedule:
    """The schedule of a named preset for ``env_id`` (a fresh object; ``none`` gives an empty fixed schedule)."""
    available = preset_names(env_id)
    if preset == "none":
        return FixedSchedule({})
    if preset not in _PRESET_TABLE[env_id]:
        plugins.load_entry_points()  # an installed plugin may register env ids and presets not loaded yet
        available = preset_names(env_id)
    if preset not in _PRESET_TABLE[env_id]:
        hint = " (the paper has no schedule for this env)" if preset == "paper" else ""
        raise AdaRLValueError(f"unknown preset {preset!r} for {env_id}{hint}; allowed presets: {available}")
    return _PRESET_TABLE[env_id][preset].from_dict(_PRESET_TABLE[env_id][preset].to_dict())


# ----------------------------------------------------------------------------------------------------------------
# Appliers: edit one live environment
# ----------------------------------------------------------------------------------------------------------------


class DynamicsApplier:
    """Applies a ``{parameter: value}`` dict to one live environment, always starting from its defaults."""

    env_id: str
    params: tuple[str, ...]

    def apply(self, values: Mapping[str, float]) -> None:
        raise NotImplementedError

    def restore(self) -> None:
        """Put the environment back to its own defaults."""
        self.apply({})


class CartPoleDynamics(DynamicsApplier):
    """gymnasium CartPole: ``length`` is the half pole length; ``polemass_length = masspole * length``."""

    def __init__(self, unwrapped: Any, env_id: str = "CartPole-v1") -> None:
        for attr in ("length", "masspole", "polemass_length"):
            if not hasattr(unwrapped, attr):
                raise AdaRLValueError(
                    f"{env_id}: the live environment {type(unwrapped).__name__} has no attribute {attr!r}; "
                    "expected gymnasium's CartPoleEnv"
                )
        self.env_id = env_id
        self.env = unwrapped
        self.params = ("pole_length",)
        self.default_length = float(unwrapped.length)

    def apply(self, values: Mapping[str, float]) -> None:
        length = float(values.get("pole_length", self.default_length))
        self.env.length = length
        self.env.polemass_length = self.env.masspole * length


class LinearCartPoleDynamics(DynamicsApplier):
    """adarl's :class:`~adarl.envs.linear_cartpole.LinearCartPoleEnv`: ``pole_length`` via ``set_pole_length``."""

    def __init__(self, env: Any, env_id: str = "LinearCartPole-v0") -> None:
        if not hasattr(env, "set_pole_length"):
            raise AdaRLValueError(
                f"{env_id}: the live environment {type(env).__name__} has no set_pole_length(); "
                "expected adarl.envs.LinearCartPoleEnv"
            )
        self.env_id = env_id
        self.env = env
        self.params = ("pole_length",)

    def apply(self, values: Mapping[str, float]) -> None:
        self.env.set_pole_length(values.get("pole_length"))


# Fields restored from the default snapshot before every application, and copied from a recompiled model in
# ``consistent`` mode (everything the compiler derives from the geometry; mj_setConst derives the rest).
_GEOMETRY_FIELDS = (
    "body_pos",
    "body_quat",
    "body_ipos",
    "body_iquat",
    "body_mass",
    "body_inertia",
    "geom_size",
    "geom_pos",
    "geom_quat",
    "geom_rbound",
    "geom_aabb",
    "bvh_aabb",
)
_OTHER_FIELDS = ("geom_friction",)
_OPT_FIELDS = ("gravity", "wind", "density", "viscosity")


class _ModelEditor:
    """Geometry edits on the live model's arrays (OMPO's way: mass and inertia stay as compiled)."""

    def __init__(self, model: Any, defaults: Mapping[str, np.ndarray]) -> None:
        self.model = model
        self.defaults = defaults

    def _element(self, kind: str, name: str) -> Any:
        try:
            return self.model.body(name) if kind == "body" else self.model.geom(name)
        except KeyError:
            raise AdaRLValueError(f"the model has no {kind} named {name!r}") from None

    def set_body_z(self, body: str, z: float) -> None:
        self._element("body", body).pos[2] = z

    def set_half_length(self, geom: str, value: float) -> None:
        self._element("geom", geom).size[1] = value

    def scale_along(self, geom: str, factor: float) -> None:
        g = self._element("geom", geom)
        g.size[1] = self.defaults["geom_size"][g.id][1] * factor
        g.pos[:] = self.defaults["geom_pos"][g.id] * factor


class _SpecEditor:
    """The same edits on an ``MjSpec`` of the model's XML (values set absolutely from the spec's originals)."""

    def __init__(self, spec: Any) -> None:
        self.spec = spec
        self.original: dict[tuple[str, str], np.ndarray] = {}

    def _element(self, kind: str, name: str) -> Any:
        element = self.spec.body(name) if kind == "body" else self.spec.geom(name)
        if element is None:
            raise AdaRLValueError(f"the model has no {kind} named {name!r}")
        return element

    def _orig(self, kind: str, name: str, attr: str) -> np.ndarray:
        key = (kind, name + "/" + attr)
        if key not in self.original:
            self.original[key] = np.array(getattr(self._element(kind, name), attr), dtype=float)
        return self.original[key]

    def set_body_z(self, body: str, z: float) -> None:
        pos = self._orig("body", body, "pos").copy()
        pos[2] = z
        self._element("body", body).pos = pos

    def set_half_length(self, geom: str, value: float) -> None:
        size = self._orig("geom", geom, "size").copy()
        size[1] = value
        self._element("geom", geom).size = size

    def scale_along(self, geom: str, factor: float) -> None:
        fromto = self._orig("geom", geom, "fromto")
        element = self._element("geom", geom)
        if np.isfinite(fromto).all():  # defined by its end points: scale them about the body origin
            element.fromto = fromto * factor
        else:
            element.size = self._orig("geom", geom, "size") * np.array([1.0, factor, 1.0])
            element.pos = self._orig("geom", geom, "pos") * factor

    def reset(self) -> None:
        for (kind, key), value in self.original.items():
            name, attr = key.rsplit("/", 1)
            setattr(self._element(kind, name), attr, value.copy())


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

#: Bound on the number of recompiled models kept per environment in ``consistent`` mode.
COMPILE_CACHE_SIZE = 256


class MujocoDynamics(DynamicsApplier):
    """Edits a live ``mujoco.MjModel`` of a gymnasium v5 environment.

    Every :meth:`apply` first restores the defaults captured at construction (so nothing compounds), then:
    geometry (``consistent``: an ``MjSpec`` of the XML is edited, compiled - cached per value set - and its
    geometry, mass and inertia arrays copied in; ``ompo``: the live arrays are edited as OMPO does), mass and
    friction scales, gravity and wind, and finally ``mj_setConst`` on a scratch ``MjData`` (fresh bounding
    radii, so contacts stay valid, and consistent derived constants; the env's own data is untouched).
    """

    def __init__(
        self,
        model: Any,
        env_id: str,
        params: tuple[str, ...],
        mode: str = "consistent",
        xml_path: str | None = None,
    ) -> None:
        import mujoco

        self._mujoco = mujoco
        self.env_id = check_env_id(env_id)
        self.mode = check_mode(mode)
        self.model = model
        self.params = tuple(params)
        self.xml_path = xml_path or default_xml_path(env_id)
        allowed = env_parameters(env_id, require=params)
        live_bodies = {model.body(i).name for i in range(1, model.nbody)} - {""}
        self._body_ids: dict[str, int] = {}
        for name in self.params:
            if name.startswith(_BODY_MASS_PREFIX):
                body = name[len(_BODY_MASS_PREFIX) :]
                if body not in live_bodies:
                    raise AdaRLValueError(
                        f"unknown parameter {name!r} for {env_id}: the model has no body {body!r}; "
                        f"allowed bodies: {sorted(live_bodies)}"
                    )
                self._body_ids[name] = model.body(body).id
            elif name not in allowed:
                raise _unknown(env_id, name, allowed)
        self._fields = tuple(f for f in _GEOMETRY_FIELDS if hasattr(model, f))  # bvh_aabb: newer MuJoCo only
        self.defaults = {f: np.array(getattr(model, f), copy=True) for f in self._fields + _OTHER_FIELDS}
        self.default_opt = {f: np.array(getattr(model.opt, f), copy=True) for f in _OPT_FIELDS}
        self.geometry = {p: e for p, e in _GEOMETRY.get(self.env_id, {}).items() if p in self.params}
        self._geo_defaults = self._geometry_defaults()
        self.uses_air = "wind" in self.params
        self._scratch = mujoco.MjData(model)
        self._spec: Any = None
        self._spec_editor: _SpecEditor | None = None
        self._cache: OrderedDict[tuple, dict[str, np.ndarray]] = OrderedDict()
        self.compiles = 0  # how many models were compiled (for tests and diagnostics)

    def _geometry_defaults(self) -> dict[str, float]:
        """What the edits get as ``defaults``: every parameter's default, and the built-in edits' own numbers."""
        m = self.model
        if not self.geometry:
            return {}
        out = {n: p.default for n, p in env_parameters(self.env_id).items() if not n.startswith(_BODY_MASS_PREFIX)}
        bodies, geoms = _REQUIRED_NAMES.get(self.env_id, ((), ()))
        try:
            for name in bodies:
                m.body(name)
            for name in geoms:
                m.geom(name)
        except KeyError as err:
            raise AdaRLValueError(
                f"{self.env_id}: the live model lacks a body or geom the geometry parameters "
                f"{sorted(self.geometry)} need ({err}); they need the gymnasium v5 model "
                f"(bodies {list(bodies)}, geoms {list(geoms)})"
            ) from err
        if "torso" in bodies:
            out["torso_z"] = float(m.body("torso").pos[2])
            out["torso_half"] = float(m.geom("torso_geom").size[1])
        return out

    def _edit(self, editor: Any, name: str, value: float) -> None:
        try:
            self.geometry[name](editor, value, self._geo_defaults)
        except AdaRLValueError as err:
            raise AdaRLValueError(f"{self.env_id}: parameter {name} = {value!r}: {err}") from err
        except Exception as err:  # noqa: BLE001 - a registered parameter's own code, named with its parameter
            raise AdaRLValueError(
                f"{self.env_id}: applying parameter {name} = {value!r} failed: {type(err).__name__}: {err}"
            ) from err

    def _is_default(self, name: str, value: float) -> bool:
        return abs(value - env_parameters(self.env_id)[name].default) <= 1e-12

    def _compiled(self, geo: dict[str, float]) -> dict[str, np.ndarray]:
        key = tuple(sorted(geo.items()))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        mujoco = self._mujoco
        if self._spec is None:
            with quiet_mujoco():
                self._spec = mujoco.MjSpec.from_file(self.xml_path)
            self._spec_editor = _SpecEditor(self._spec)
        editor = self._spec_editor
        editor.reset()
        for name, value in geo.items():
            self._edit(editor, name, value)
        with quiet_mujoco():
            compiled = self._spec.compile()
        self.compiles += 1
        arrays = {}
        for f in self._fields:
            new, live = getattr(compiled, f), getattr(self.model, f)
            if new.shape != live.shape:
                raise AdaRLValueError(
                    f"{self.env_id}: the model recompiled from {self.xml_path} does not match the live model "
                    f"({f} has shape {new.shape}, live {live.shape}); use mode='ompo' for a customised model"
                )
            arrays[f] = np.array(new, copy=True)
        self._cache[key] = arrays
        if len(self._cache) > COMPILE_CACHE_SIZE:
            self._cache.popitem(last=False)
        return arrays

    def apply(self, values: Mapping[str, float]) -> None:
        mujoco, model = self._mujoco, self.model
        for f, default in self.defaults.items():
            getattr(model, f)[...] = default
        for f, default in self.default_opt.items():
            if default.ndim:
                getattr(model.opt, f)[:] = default
            else:
                setattr(model.opt, f, float(default))

        geo = {p: float(values[p]) for p in self.geometry if p in values and not self._is_default(p, values[p])}
        if geo:
            if self.mode == "consistent":
                for f, array in self._compiled(geo).items():
                    getattr(model, f)[...] = array
            else:
                editor = _ModelEditor(model, self.defaults)
                for name, value in geo.items():
                    self._edit(editor, name, value)

        scale = np.ones(model.nbody)
        if "mass_scale" in values:
            scale *= float(values["mass_scale"])
        for name, body_id in self._body_ids.items():
            if name in values:
                scale[body_id] *= float(values[name])
        if (scale != 1.0).any():
            model.body_mass[:] *= scale
            model.body_inertia[:] *= scale[:, None]
        if "friction_scale" in values:
            model.geom_friction[:] *= float(values["friction_scale"])
        if "gravity" in values:
            model.opt.gravity[:] = (0.0, 0.0, -float(values["gravity"]))
        if self.uses_air:
            model.opt.density = AIR_DENSITY
            model.opt.viscosity = AIR_VISCOSITY
            model.opt.wind[:] = (-float(values.get("wind", 0.0)), 0.0, 0.0)
        mujoco.mj_setConst(model, self._scratch)


class _LiveEnvDynamics(DynamicsApplier):
    """A registered env without a MuJoCo model file: each parameter's ``apply(env, value, defaults)`` on the live
    (unwrapped) gymnasium env, every time with every parameter (its default when not given), so nothing compounds.
    """

    def __init__(self, unwrapped: Any, env_id: str, params: tuple[str, ...]) -> None:
        allowed = env_parameters(env_id, require=params)
        for name in params:
            if name not in allowed:
                raise _unknown(env_id, name, allowed)
        self.env_id = env_id
        self.env = unwrapped
        self.params = tuple(params)
        self.edits = {p: _GEOMETRY[env_id][p] for p in self.params}
        self.defaults = {n: p.default for n, p in allowed.items()}

    def apply(self, values: Mapping[str, float]) -> None:
        for name, edit in self.edits.items():
            value = float(values.get(name, self.defaults[name]))
            try:
                edit(self.env, value, self.defaults)
            except AdaRLValueError:
                raise
            except Exception as err:  # noqa: BLE001 - a registered parameter's own code, named with its parameter
                raise AdaRLValueError(
                    f"{self.env_id}: applying parameter {name} = {value!r} failed: {type(err).__name__}: {err}"
                ) from err


def make_applier(env_id: str, unwrapped: Any, params: tuple[str, ...], mode: str = "consistent") -> DynamicsApplier:
    """The applier for a live (unwrapped) gymnasium environment."""
    env_id = check_env_id(env_id)
    check_mode(mode)
    if env_id == "CartPole-v1":
        return CartPoleDynamics(unwrapped, env_id)
    if env_id == "LinearCartPole-v0":
        return LinearCartPoleDynamics(unwrapped, env_id)
    if env_id in _REGISTERED and env_id not in _MUJOCO_XML:
        return _LiveEnvDynamics(unwrapped, env_id, params)
    model = getattr(unwrapped, "model", None)
    if model is None or not hasattr(model, "body_mass"):
        raise AdaRLValueError(
            f"{env_id}: the live environment {type(unwrapped).__name__} has no MuJoCo model (`.model`); "
            f"supported: {list(_known_envs())}"
        )
    return MujocoDynamics(model, env_id, params, mode, xml_path=getattr(unwrapped, "fullpath", None))
