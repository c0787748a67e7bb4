"""Any gymnasium env, and the perturbation parameters a recipe declares itself (``env.parameters``).

adarl's own env ids (:mod:`adarl.envs.registry`) come with presets and parameters written for their models. Any
other id in gymnasium's registry runs too: with plain dynamics (``env.perturbation.preset: none``), or with a
schedule over parameters the recipe declares, each a named entry of a MuJoCo model field::

    env:
      id: HalfCheetah-v5
      parameters:
        torso_mass: {field: body_mass, index: torso, low: 1.0, high: 20.0}
        gravity_z: {field: opt.gravity, index: 2}

Why apart from the registry: what a declared parameter is (a field, an index) is checked here twice, by name when a
recipe is validated (no MuJoCo: :data:`MODEL_FIELDS`) and against the loaded model when the env is built
(:func:`resolve_field`: the index's range, a body or geom name). gymnasium is imported only when an id is not
adarl's own, never at module top (recipes validate without it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from adarl.errors import AdaRLValueError, did_you_mean, one_of

__all__ = [
    "MODEL_FIELDS",
    "FieldParameter",
    "declared_parameters",
    "declared_dict",
    "gymnasium_ids",
    "gymnasium_entry_point",
    "resolve_field",
    "FieldSlot",
]

#: MuJoCo model fields a declared parameter may set, and what their rows are (a row may be given by that element's
#: name); ``opt.*`` are the physics options (``opt.gravity`` and ``opt.wind`` are 3-vectors, the rest scalars).
MODEL_FIELDS: dict[str, str | None] = {
    "body_mass": "body",
    "body_inertia": "body",
    "body_pos": "body",
    "geom_size": "geom",
    "geom_pos": "geom",
    "geom_friction": "geom",
    "dof_damping": "dof",
    "dof_armature": "dof",
    "dof_frictionloss": "dof",
    "jnt_stiffness": "joint",
    "jnt_range": "joint",
    "actuator_gear": "actuator",
    "actuator_ctrlrange": "actuator",
    "opt.gravity": None,
    "opt.wind": None,
    "opt.timestep": None,
    "opt.density": None,
    "opt.viscosity": None,
}

_KEYS = ("field", "index", "low", "high")


@dataclass(frozen=True)
class FieldParameter:
    """One declared parameter: ``value`` is written to ``model.<field>[index]`` at every reset (absolutely: every
    episode starts from the model's own values), after adarl's own parameters. ``index``: one entry per dimension
    of the field (a row may be an element's name, e.g. ``torso``); ``low``/``high``: the values a schedule may
    reach (unbounded when None)."""

    name: str
    field: str
    index: tuple[int | str, ...] = ()
    low: float | None = None
    high: float | None = None

    def as_dict(self) -> dict:
        out: dict[str, Any] = {"field": self.field}
        if self.index:
            out["index"] = list(self.index) if len(self.index) > 1 else self.index[0]
        if self.low is not None:
            out["low"] = self.low
        if self.high is not None:
            out["high"] = self.high
        return out


def _index(name: str, value: Any) -> tuple[int | str, ...]:
    items = [] if value is None else list(value) if isinstance(value, (list, tuple)) else [value]
    if len(items) > 2:
        raise AdaRLValueError(
            f"env.parameters.{name}.index: at most two entries (row, column), got {value!r}; e.g. index: torso or "
            "index: [torso, 1]"
        )
    for item in items:
        if isinstance(item, bool) or not isinstance(item, (int, str, np.integer)) or item == "":
            raise AdaRLValueError(
                f"env.parameters.{name}.index: each entry must be an integer or an element's name, got {item!r}"
            )
    return tuple(int(i) if isinstance(i, (int, np.integer)) else i for i in items)


def _bound(name: str, key: str, value: Any) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise AdaRLValueError(f"env.parameters.{name}.{key} must be a finite number or null, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise AdaRLValueError(f"env.parameters.{name}.{key} must be a finite number or null, got {value!r}")
    return value


def _one(name: Any, spec: Any) -> FieldParameter:
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(
            f"env.parameters: a parameter name must be an identifier (letters, digits, _), got {name!r}"
        )
    if isinstance(spec, FieldParameter):
        spec = spec.as_dict()
    if not isinstance(spec, Mapping):
        raise AdaRLValueError(
            f"env.parameters.{name} must be a mapping {{field, index?, low?, high?}}, got {spec!r}; e.g. "
            "{field: body_mass, index: torso}"
        )
    unknown = [k for k in spec if k not in _KEYS]
    if unknown:
        raise AdaRLValueError(
            f"env.parameters.{name}: unknown key {unknown[0]!r}; allowed: {one_of(_KEYS)}"
            f"{did_you_mean(str(unknown[0]), _KEYS)}"
        )
    field = spec.get("field")
    if field not in MODEL_FIELDS:
        raise AdaRLValueError(
            f"env.parameters.{name}.field: unknown MuJoCo model field {field!r}; allowed: {one_of(MODEL_FIELDS)}"
            f"{did_you_mean(str(field), MODEL_FIELDS)}"
        )
    low, high = _bound(name, "low", spec.get("low")), _bound(name, "high", spec.get("high"))
    if low is not None and high is not None and not low < high:
        raise AdaRLValueError(f"env.parameters.{name}: low ({low:g}) must be < high ({high:g})")
    return FieldParameter(name, field, _index(name, spec.get("index")), low, high)


def declared_parameters(spec: Mapping[str, Any] | None) -> dict[str, FieldParameter]:
    """``env.parameters`` (``{name: {field, index?, low?, high?}}``) checked by name: the fields are MuJoCo model
    fields (:data:`MODEL_FIELDS`); the indices are checked against the model when the env is built."""
    if spec is None:
        return {}
    if not isinstance(spec, Mapping):
        raise AdaRLValueError(
            f"env.parameters must be a mapping {{name: {{field, index?, low?, high?}}}}, got {spec!r}"
        )
    return {name: _one(name, value) for name, value in spec.items()}


def declared_dict(spec: Mapping[str, Any] | None) -> dict[str, dict] | None:
    """The plain, picklable form of ``env.parameters`` (what a worker process is given), None when empty."""
    params = declared_parameters(spec)
    return {name: p.as_dict() for name, p in params.items()} or None


def gymnasium_ids() -> tuple[str, ...]:
    """Every id in gymnasium's registry (imports gymnasium)."""
    import gymnasium

    return tuple(gymnasium.registry)


def gymnasium_entry_point(env_id: str) -> str:
    """The entry point gymnasium registered ``env_id`` with (``""`` when it is a callable or unknown)."""
    import gymnasium

    spec = gymnasium.registry.get(env_id)
    entry = getattr(spec, "entry_point", None)
    return entry if isinstance(entry, str) else ""


def _row(model: Any, param: FieldParameter, kind: str | None, row: int | str, size: int) -> int:
    if isinstance(row, str):
        lookup = {"body": model.body, "geom": model.geom, "joint": model.joint, "actuator": model.actuator}.get(kind)
        if lookup is None:
            raise AdaRLValueError(
                f"env.parameters.{param.name}: rows of {param.field} have no names; give an integer index in "
                f"[0, {size - 1}]"
            )
        try:
            return int(lookup(row).id)
        except KeyError:
            count = {"body": model.nbody, "geom": model.ngeom, "joint": model.njnt, "actuator": model.nu}[kind]
            names = [n for n in (lookup(i).name for i in range(count)) if n]
            raise AdaRLValueError(
                f"env.parameters.{param.name}: the model has no {kind} named {row!r}; allowed: {names}"
                f"{did_you_mean(row, names)}"
            ) from None
    if not -size <= row < size:
        raise AdaRLValueError(
            f"env.parameters.{param.name}.index: {row} is out of range for {param.field} of this model; allowed: "
            f"0 to {size - 1}" + (f" (or a {kind}'s name)" if kind else "")
        )
    return int(row) % size


class FieldSlot:
    """One scalar of a live model a declared parameter sets: :meth:`get` and :meth:`set` (an ``opt`` scalar such
    as ``opt.timestep`` is an attribute, the rest entries of the model's arrays, which the bindings share)."""

    def __init__(self, owner: Any, attr: str, index: tuple[int, ...]) -> None:
        self.owner, self.attr, self.index = owner, attr, index

    def get(self) -> float:
        value = getattr(self.owner, self.attr)
        return float(value[self.index]) if self.index else float(value)

    def set(self, value: float) -> None:
        if self.index:
            getattr(self.owner, self.attr)[self.index] = value
        else:
            setattr(self.owner, self.attr, float(value))


def resolve_field(model: Any, param: FieldParameter) -> FieldSlot:
    """Where ``param`` lives in a live ``mujoco.MjModel`` (a :class:`FieldSlot`). An index of the wrong length or
    out of range, or a name the model lacks, is refused naming what is allowed."""
    owner, attr = (model.opt, param.field[4:]) if param.field.startswith("opt.") else (model, param.field)
    shape = np.shape(getattr(owner, attr))
    if len(param.index) != len(shape):
        want = "no index (a scalar)" if not shape else f"{len(shape)} entr{'y' if len(shape) == 1 else 'ies'}"
        raise AdaRLValueError(
            f"env.parameters.{param.name}: {param.field} has shape {list(shape)} in this model; its index needs "
            f"{want}, got {list(param.index)}"
        )
    kind = MODEL_FIELDS[param.field]
    index = tuple(
        _row(model, param, kind if axis == 0 else None, entry, shape[axis]) for axis, entry in enumerate(param.index)
    )
    return FieldSlot(owner, attr, index)
