"""How installed packages add env ids and perturbation parameters: :func:`register_env`, :func:`register_parameter`.

Why apart from the lookups (:mod:`adarl.envs.registry`): a registration changes several tables at once (ids, model
files, parameters and their edits, presets), all or nothing: a failed :func:`register_env` puts every table back as
it was (:func:`_registry_state`, :func:`_restore_registry`, which tests use too). :func:`register_env` and
:func:`register_parameter` are public names of :mod:`adarl.envs` and :mod:`adarl` too; installed packages reach them
through the ``adarl.plugins`` entry-point group (docs/adding-a-component.md).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from typing import Any

from adarl import plugins
from adarl.envs.presets import PRESETS, generic_presets
from adarl.envs.registry import (
    _BODY_MASS_PREFIX,
    _GEOMETRY,
    _MUJOCO_XML,
    _PRESET_TABLE,
    _REGISTERED,
    _SPECIFIC,
    ENV_IDS,
    SUPPORTED_ENVS,
    ParameterApply,
    ParameterInfo,
    _body_names,
    _check_schedule,
    _gymnasium_assets,
    _parameters,
    _RegisteredEnv,
    check_env_id,
)
from adarl.envs.schedules import FixedSchedule, Schedule, as_schedule
from adarl.errors import AdaRLValueError

__all__ = ["register_env", "register_parameter"]

# The parameters registered on any env (by whom), and the registered envs whose 'nominal' preset follows their
# parameters' defaults.
_PARAMETER_PROVIDERS: dict[tuple[str, str], str] = {}
_DERIVED_NOMINAL: set[str] = set()
# Built-in envs with an applier of their own (no MuJoCo model to edit): registered parameters would never apply.
_OWN_APPLIER = ("CartPole-v1", "LinearCartPole-v0")
# Parameters MujocoDynamics applies itself (by name, whatever the env): a registered one would be applied twice.
_RESERVED = ("mass_scale", "friction_scale", "gravity", "wind", "episode")


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


def _tables() -> dict[str, Any]:
    """Every table :func:`register_env` and :func:`register_parameter` change, by name (the objects themselves)."""
    return {
        "_MUJOCO_XML": _MUJOCO_XML,
        "_SPECIFIC": _SPECIFIC,
        "_GEOMETRY": _GEOMETRY,
        "_PRESET_TABLE": _PRESET_TABLE,
        "_REGISTERED": _REGISTERED,
        "_PARAMETER_PROVIDERS": _PARAMETER_PROVIDERS,
        "_DERIVED_NOMINAL": _DERIVED_NOMINAL,
    }


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
    tables = _tables()
    for name, saved in state.items():
        tables[name].clear()
        tables[name].update(saved)
    _body_names.cache_clear()


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
    _PARAMETER_PROVIDERS[(env_id, name)] = plugins.current_provider() or "register_parameter"
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
    ENV_IDS.check_free(env_id, replace=replace)
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
        ENV_IDS.register(
            env_id, _RegisteredEnv(env_id, path, str(description), plugins.current_provider()), replace=True
        )
        _PRESET_TABLE[env_id] = {}
        for info, apply in pairs:
            register_parameter(env_id, info, apply)
        if presets is None and path is not None:
            _PRESET_TABLE[env_id].update({k: v for k, v in generic_presets().items() if k != "nominal"})
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
