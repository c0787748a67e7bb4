"""Episode schedules: which dynamics parameters an episode gets, as a function of its index (and an RNG).

Every schedule maps ``(episode_index, rng) -> {parameter: value}`` and knows the centre of the set of values it
can produce (:meth:`Schedule.nominal`, the "nominal dynamics" the paper evaluates on) and the smallest box that
contains them (:meth:`Schedule.bounds`, used to validate a schedule against an environment before it runs).
Schedules are plain, JSON-able descriptions: ``schedule_from_dict(s.to_dict()) == s``.

=====================  ==========================================================================================
``SinusoidSchedule``   paper D.3: ``value = center + amplitude * sin(frequency * i + phase)``; deterministic
``UniformSchedule``    a box (paper Table 2): each parameter drawn independently from ``U[low, high]``
``FixedSchedule``      always the same values (nominal dynamics, or one point of a sweep)
``ListSchedule``       an explicit list (or grid) of value dicts, episode ``i`` gets entry ``i mod len``
=====================  ==========================================================================================
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from adarl.errors import NO_VALUE, AdaRLValueError, did_you_mean, one_of

__all__ = [
    "Schedule",
    "SinusoidSchedule",
    "UniformSchedule",
    "FixedSchedule",
    "ListSchedule",
    "SCHEDULE_KINDS",
    "schedule_from_dict",
    "as_schedule",
    "grid_schedule",
    "schedule_problems",
    "schedule_parameter_paths",
    "schedule_parameter_names",
]


def _number(value: Any, what: str) -> float:
    """A finite real number (bools refused), as a Python float."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise AdaRLValueError(f"{what} must be a finite number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise AdaRLValueError(f"{what} must be a finite number, got {value!r}")
    return value


def _values(mapping: Any, what: str) -> dict[str, float]:
    """A ``{name: finite float}`` dict with string keys, in sorted key order."""
    if not isinstance(mapping, Mapping):
        raise AdaRLValueError(f"{what} must be a mapping {{parameter: value}}, got {mapping!r}")
    for key in mapping:
        if not isinstance(key, str) or not key:
            raise AdaRLValueError(f"{what}: parameter names must be non-empty strings, got {key!r}")
    return {key: _number(mapping[key], f"{what}[{key!r}]") for key in sorted(mapping)}


def _same_keys(a: Mapping, b: Mapping, what_a: str, what_b: str, schedule: str) -> None:
    if set(a) != set(b):
        raise AdaRLValueError(
            f"{schedule}: {what_a} and {what_b} must name the same parameters, got {sorted(a)} and {sorted(b)}"
        )


class Schedule(ABC):
    """Base class. Subclasses set ``kind`` and implement sample / nominal / bounds / to_dict / from_dict."""

    kind: ClassVar[str] = ""
    #: whether :meth:`sample` consumes the RNG (so different seeds / workers give different sequences)
    is_random: ClassVar[bool] = False

    @property
    @abstractmethod
    def params(self) -> tuple[str, ...]:
        """The parameter names this schedule sets (sorted)."""

    @abstractmethod
    def sample(self, episode_index: int, rng: np.random.Generator) -> dict[str, float]:
        """The values for episode ``episode_index`` (0-based); random schedules draw from ``rng``."""

    @abstractmethod
    def nominal(self) -> dict[str, float]:
        """The centre of the uncertainty set (the paper's "nominal dynamics")."""

    @abstractmethod
    def bounds(self) -> dict[str, tuple[float, float]]:
        """``{param: (min, max)}``: the smallest box holding every value the schedule can produce."""

    @abstractmethod
    def to_dict(self) -> dict:
        """A JSON-able description, ``{"kind": ..., ...}``; :func:`schedule_from_dict` inverts it."""

    @classmethod
    @abstractmethod
    def _from_fields(cls, fields: dict) -> Schedule:
        """Build from the dict's fields (``kind`` removed, unknown keys already refused)."""

    _fields: ClassVar[tuple[str, ...]] = ()
    _required: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_dict(cls, data: Mapping) -> Schedule:
        """Inverse of :meth:`to_dict`. ``kind`` may be omitted when called on the subclass itself."""
        if not isinstance(data, Mapping):
            raise AdaRLValueError(f"a schedule description must be a mapping, got {data!r}")
        fields = dict(data)
        kind = fields.pop("kind", cls.kind)
        if cls is Schedule:
            return schedule_from_dict(data)
        if kind != cls.kind:
            raise AdaRLValueError(f"{cls.__name__}.from_dict: kind must be {cls.kind!r}, got {kind!r}")
        unknown = sorted(set(fields) - set(cls._fields))
        if unknown:
            raise AdaRLValueError(
                f"{cls.kind} schedule: unknown key(s) {unknown}; allowed keys: {['kind', *cls._fields]}"
            )
        missing = [k for k in cls._required if k not in fields]
        if missing:
            raise AdaRLValueError(f"{cls.kind} schedule: missing key(s) {missing}; required: {list(cls._required)}")
        return cls._from_fields(fields)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Schedule) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(repr(self.to_dict()))

    def __repr__(self) -> str:
        fields = {k: v for k, v in self.to_dict().items() if k != "kind"}
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in fields.items())})"


class SinusoidSchedule(Schedule):
    """Paper D.3: ``value_p(i) = center_p + amplitude_p * sin(frequency_p * i + phase_p)``.

    ``frequency`` and ``phase`` are either one number for all parameters or a dict per parameter.
    Deterministic: the RNG is not used.

    >>> schedule = SinusoidSchedule(center={"torso_length": 0.4}, amplitude={"torso_length": 0.1}, frequency=0.5)
    >>> [round(schedule.sample(i)["torso_length"], 3) for i in range(4)]  # episodes 0..3
    [0.4, 0.448, 0.484, 0.5]
    >>> schedule.nominal()  # the centre of the uncertainty set: where evaluations run
    {'torso_length': 0.4}
    >>> schedule_from_dict(schedule.to_dict()) == schedule  # the recipe's ``schedule:`` mapping
    True
    """

    kind = "sinusoid"
    _fields = ("center", "amplitude", "frequency", "phase")
    _required = ("center", "amplitude", "frequency")

    def __init__(
        self,
        center: Mapping[str, float],
        amplitude: Mapping[str, float],
        frequency: float | Mapping[str, float],
        phase: float | Mapping[str, float] = 0.0,
    ) -> None:
        name = type(self).__name__
        self.center = _values(center, f"{name}: center")
        self.amplitude = _values(amplitude, f"{name}: amplitude")
        _same_keys(self.center, self.amplitude, "center", "amplitude", name)
        self.frequency = self._per_param(frequency, "frequency")
        self.phase = self._per_param(phase, "phase")

    def _per_param(self, value, what: str) -> float | dict[str, float]:
        name = type(self).__name__
        if isinstance(value, Mapping):
            out = _values(value, f"{name}: {what}")
            _same_keys(self.center, out, "center", what, name)
            return out
        return _number(value, f"{name}: {what}")

    def _get(self, field: float | dict[str, float], param: str) -> float:
        return field[param] if isinstance(field, dict) else field

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(self.center)

    def sample(self, episode_index: int, rng: np.random.Generator | None = None) -> dict[str, float]:
        i = int(episode_index)
        return {
            p: self.center[p]
            + self.amplitude[p] * math.sin(self._get(self.frequency, p) * i + self._get(self.phase, p))
            for p in self.params
        }

    def nominal(self) -> dict[str, float]:
        return dict(self.center)

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {
            p: (self.center[p] - abs(self.amplitude[p]), self.center[p] + abs(self.amplitude[p])) for p in self.params
        }

    def to_dict(self) -> dict:
        out = {
            "kind": self.kind,
            "center": dict(self.center),
            "amplitude": dict(self.amplitude),
            "frequency": dict(self.frequency) if isinstance(self.frequency, dict) else self.frequency,
        }
        if self.phase != 0.0:
            out["phase"] = dict(self.phase) if isinstance(self.phase, dict) else self.phase
        return out

    @classmethod
    def _from_fields(cls, fields: dict) -> SinusoidSchedule:
        return cls(**fields)


class UniformSchedule(Schedule):
    """A box (paper Table 2): each parameter independently ``U[low_p, high_p]`` per episode."""

    kind = "uniform"
    is_random = True
    _fields = ("low", "high")
    _required = ("low", "high")

    def __init__(self, low: Mapping[str, float], high: Mapping[str, float]) -> None:
        name = type(self).__name__
        self.low = _values(low, f"{name}: low")
        self.high = _values(high, f"{name}: high")
        _same_keys(self.low, self.high, "low", "high", name)
        for p in self.low:
            if self.low[p] > self.high[p]:
                raise AdaRLValueError(
                    f"{name}: low[{p!r}]={self.low[p]} is above high[{p!r}]={self.high[p]}; need low <= high"
                )

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(self.low)

    def sample(self, episode_index: int, rng: np.random.Generator) -> dict[str, float]:
        # One draw per parameter, in sorted name order, so a sequence depends only on the seed.
        return {p: float(rng.uniform(self.low[p], self.high[p])) for p in self.params}

    def nominal(self) -> dict[str, float]:
        return {p: 0.5 * (self.low[p] + self.high[p]) for p in self.params}

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {p: (self.low[p], self.high[p]) for p in self.params}

    def to_dict(self) -> dict:
        return {"kind": self.kind, "low": dict(self.low), "high": dict(self.high)}

    @classmethod
    def _from_fields(cls, fields: dict) -> UniformSchedule:
        return cls(**fields)


class FixedSchedule(Schedule):
    """The same values every episode (nominal dynamics, or one point of a sweep). ``{}`` sets nothing."""

    kind = "fixed"
    _fields = ("values",)
    _required = ("values",)

    def __init__(self, values: Mapping[str, float]) -> None:
        self.values = _values(values, f"{type(self).__name__}: values")

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(self.values)

    def sample(self, episode_index: int, rng: np.random.Generator | None = None) -> dict[str, float]:
        return dict(self.values)

    def nominal(self) -> dict[str, float]:
        return dict(self.values)

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {p: (v, v) for p, v in self.values.items()}

    def to_dict(self) -> dict:
        return {"kind": self.kind, "values": dict(self.values)}

    @classmethod
    def _from_fields(cls, fields: dict) -> FixedSchedule:
        return cls(**fields)


class ListSchedule(Schedule):
    """An explicit list of value dicts (all naming the same parameters).

    Episode ``i`` gets ``values[i % len(values)]`` when ``cycle`` (the default); with ``cycle=False`` the list is
    played once and its last entry then repeats (a collector always resets once more after the last episode, so
    running past the end must not fail). :meth:`nominal` is the mean of the entries (the centroid of the set).
    """

    kind = "list"
    _fields = ("values", "cycle")
    _required = ("values",)

    def __init__(self, values: Sequence[Mapping[str, float]], cycle: bool = True) -> None:
        name = type(self).__name__
        if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Sequence) or len(values) == 0:
            raise AdaRLValueError(
                f"{name}: values must be a non-empty list of {{parameter: value}} dicts, got {values!r}"
            )
        self.values = [_values(v, f"{name}: values[{k}]") for k, v in enumerate(values)]
        for k, v in enumerate(self.values[1:], start=1):
            _same_keys(self.values[0], v, "values[0]", f"values[{k}]", name)
        if not isinstance(cycle, bool):
            raise AdaRLValueError(f"{name}: cycle must be true or false, got {cycle!r}")
        self.cycle = cycle

    def __len__(self) -> int:
        return len(self.values)

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(self.values[0])

    def sample(self, episode_index: int, rng: np.random.Generator | None = None) -> dict[str, float]:
        i = int(episode_index)
        k = i % len(self.values) if self.cycle else min(max(i, 0), len(self.values) - 1)
        return dict(self.values[k])

    def nominal(self) -> dict[str, float]:
        return {p: float(np.mean([v[p] for v in self.values])) for p in self.params}

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {p: (min(v[p] for v in self.values), max(v[p] for v in self.values)) for p in self.params}

    def to_dict(self) -> dict:
        return {"kind": self.kind, "values": [dict(v) for v in self.values], "cycle": self.cycle}

    @classmethod
    def _from_fields(cls, fields: dict) -> ListSchedule:
        return cls(**fields)


SCHEDULE_KINDS: dict[str, type[Schedule]] = {
    cls.kind: cls for cls in (SinusoidSchedule, UniformSchedule, FixedSchedule, ListSchedule)
}


def schedule_from_dict(data: Mapping) -> Schedule:
    """Build a schedule from ``{"kind": "sinusoid" | "uniform" | "fixed" | "list", ...}`` (see each class)."""
    if not isinstance(data, Mapping):
        raise AdaRLValueError(
            f"a schedule description must be a mapping with a 'kind' in {sorted(SCHEDULE_KINDS)}, got {data!r}"
        )
    kind = data.get("kind")
    if kind not in SCHEDULE_KINDS:
        raise AdaRLValueError(f"unknown schedule kind {kind!r}; allowed kinds: {sorted(SCHEDULE_KINDS)}")
    return SCHEDULE_KINDS[kind].from_dict(data)


def as_schedule(obj: Schedule | Mapping) -> Schedule:
    """A :class:`Schedule` as is, or one built from its dict description."""
    if isinstance(obj, Schedule):
        return obj
    if isinstance(obj, Mapping):
        return schedule_from_dict(obj)
    raise AdaRLValueError(
        f"expected a Schedule or its dict description ({{'kind': one of {sorted(SCHEDULE_KINDS)}, ...}}), got {obj!r}"
    )


def grid_schedule(axes: Mapping[str, Sequence[float]], cycle: bool = False) -> ListSchedule:
    """A :class:`ListSchedule` over the Cartesian product of per-parameter value lists (for evaluation sweeps).

    ``grid_schedule({"torso_length": [0.3, 0.4], "foot_length": [0.3, 0.4]})`` has 4 entries.
    """
    if not isinstance(axes, Mapping) or not axes:
        raise AdaRLValueError(f"grid_schedule: axes must be a non-empty {{parameter: [values]}} mapping, got {axes!r}")
    names = sorted(axes)
    for n in names:
        if isinstance(axes[n], (str, bytes)) or not isinstance(axes[n], Sequence) or not len(axes[n]):
            raise AdaRLValueError(f"grid_schedule: axes[{n!r}] must be a non-empty list of numbers, got {axes[n]!r}")
    entries = [dict(zip(names, combo)) for combo in itertools.product(*(axes[n] for n in names))]
    return ListSchedule(entries, cycle=cycle)


# ---------------------------------------------------------------- the grammar, checked with key paths


def _is_finite_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _check_param_map(where: str, m: Any, problems: list) -> bool:
    if not isinstance(m, Mapping):
        problems.append((where, m, "must be a mapping {parameter: number}"))
        return False
    ok = True
    for k, x in m.items():
        if not isinstance(k, str) or not k:
            problems.append((where, m, f"parameter names must be non-empty strings, got {k!r}"))
            ok = False
        elif not _is_finite_number(x):
            problems.append((f"{where}.{k}", x, "must be a finite number"))
            ok = False
    return ok


def _same_params(where: str, m: Mapping, ref: Mapping, ref_name: str, problems: list) -> None:
    if set(m) != set(ref):
        problems.append((where, m, f"must name the same parameters as {ref_name}: {sorted(map(str, ref))}"))


def schedule_problems(s: Mapping) -> list[tuple[str, Any, str]]:
    """Every problem with a schedule description, as ``(key path, value, message)`` (``[]``: it is well formed).

    The grammar of :func:`schedule_from_dict` (each kind's keys, from the classes) checked with key paths in the
    messages, so that a recipe reports ``schedule.high.torso_length`` rather than a constructor's message. Parameter
    names and ranges belong to the env: :func:`adarl.envs.registry.validate_schedule` checks them.

    >>> schedule_problems({"kind": "uniform", "low": {"torso_length": 0.5}, "high": {"torso_length": 0.3}})
    [('high.torso_length', 0.3, 'must be >= low.torso_length (0.5)')]
    """
    problems: list[tuple[str, Any, str]] = []
    kind = s.get("kind", NO_VALUE)
    kinds = list(SCHEDULE_KINDS)
    if kind is NO_VALUE:
        return [("kind", NO_VALUE, f"is required: one of {one_of(kinds)}")]
    if not isinstance(kind, str) or kind not in SCHEDULE_KINDS:
        return [("kind", kind, f"must be one of {one_of(kinds)}{did_you_mean(str(kind), kinds)}")]
    required, allowed = SCHEDULE_KINDS[kind]._required, ["kind", *SCHEDULE_KINDS[kind]._fields]
    for k in s:
        if k not in allowed:
            problems.append(
                (
                    str(k),
                    s[k],
                    f"unknown key for a {kind} schedule; allowed: {one_of(allowed)}{did_you_mean(str(k), allowed)}",
                )
            )
    for k in required:
        if k not in s:
            problems.append((k, NO_VALUE, f"is required by a {kind} schedule"))
    if problems:
        return problems
    if kind == "sinusoid":
        ok_c = _check_param_map("center", s["center"], problems)
        if _check_param_map("amplitude", s["amplitude"], problems) and ok_c:
            _same_params("amplitude", s["amplitude"], s["center"], "center", problems)
        for key in ("frequency", "phase"):
            if key not in s:
                continue
            v = s[key]
            if isinstance(v, Mapping):
                if _check_param_map(key, v, problems) and ok_c:
                    _same_params(key, v, s["center"], "center", problems)
            elif not _is_finite_number(v):
                problems.append(
                    (key, v, "must be a finite number (radians per episode) or a mapping {parameter: number}")
                )
    elif kind == "uniform":
        ok_lo = _check_param_map("low", s["low"], problems)
        if _check_param_map("high", s["high"], problems) and ok_lo:
            if set(s["low"]) != set(s["high"]):
                _same_params("high", s["high"], s["low"], "low", problems)
            else:
                for k, lo in s["low"].items():
                    if s["high"][k] < lo:
                        problems.append((f"high.{k}", s["high"][k], f"must be >= low.{k} ({lo})"))
    elif kind == "fixed":
        _check_param_map("values", s["values"], problems)
    else:  # list
        vals = s["values"]
        if not isinstance(vals, list) or not vals:
            problems.append(("values", vals, "must be a non-empty list of mappings {parameter: number}"))
        else:
            oks = [_check_param_map(f"values[{i}]", m, problems) for i, m in enumerate(vals)]
            if all(oks):
                for i, m in enumerate(vals[1:], 1):
                    _same_params(f"values[{i}]", m, vals[0], "values[0]", problems)
        if "cycle" in s and not isinstance(s["cycle"], bool):
            problems.append(("cycle", s["cycle"], "must be true or false"))
    return problems


def schedule_parameter_paths(s: Mapping) -> list[tuple[str, Any]]:
    """``(key path, parameter name)`` of every parameter a schedule description names, each name once (at its
    first use), e.g. ``[("center.torso_length", "torso_length")]``."""
    out = []
    for field in ("center", "amplitude", "frequency", "phase", "low", "high"):
        if isinstance(s.get(field), Mapping):
            out += [(f"{field}.{k}", k) for k in s[field]]
    vals = s.get("values")
    if isinstance(vals, Mapping):
        out += [(f"values.{k}", k) for k in vals]
    elif isinstance(vals, list):
        for i, m in enumerate(vals):
            if isinstance(m, Mapping):
                out += [(f"values[{i}].{k}", k) for k in m]
    seen, unique = set(), []
    for where, k in out:  # report each unknown name once, at its first use
        if k not in seen:
            seen.add(k)
            unique.append((where, k))
    return unique


def schedule_parameter_names(s: Mapping) -> set[str]:
    """The parameter names a schedule description sets."""
    return {str(k) for _, k in schedule_parameter_paths(s)}
