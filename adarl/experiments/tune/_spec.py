"""Hyperparameter-search specs (``adarl tune``): a base recipe, a search space over recipe keys, the objective, the
trial budget, the sampler and the pruner; validated in full before any trial runs.

A spec is a YAML file with ``kind: tune`` (the shipped ones: ``adarl recipes`` lists them, by name)::

    kind: tune
    name: cartpole_beta
    recipe: linear_cartpole_sac
    overrides: [collector.total_frames=4000]
    seeds: [0, 1]          # or seed: 0 (one run per trial, the default)
    space:
      rank.beta: {type: float, low: 0.8, high: 0.99}
      algorithm.lr: {type: float, low: 1.0e-4, high: 3.0e-3, log: true}
      rank.interval: {type: int, low: 1000, high: 3000, step: 1000}
      replay.warm_start.mode: {type: categorical, choices: [refill, keep]}
    objective: {metric: score, score_last: 2}
    n_trials: 8
    sampler: {name: tpe, seed: 0}
    pruner: {name: median}

``space: default`` (or no ``space``) is the default space of the recipe's algorithm (and rank rule):
:mod:`adarl.experiments.tune._defaults`, resolved against the recipe by :func:`resolve_space`; :func:`tune_target`
also makes a spec of a bare recipe (``adarl tune RECIPE``).

:func:`load_tune_spec` reads the file and checks its own keys (did-you-mean for a misspelt one, allowed values for a
name); :func:`check_space` checks every search-space key against the recipe: the key must exist and each end of its
range (each choice) must validate as a value of it, by building the recipe with it. Nothing here imports Optuna:
:mod:`adarl.experiments.tune._study` runs the study.
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from adarl.envs.registry import parameters_for
from adarl.errors import RecipeError, did_you_mean
from adarl.experiments.spec import SweepSpec, run_own_key
from adarl.experiments.sweep import parse_sweep
from adarl.experiments.tune._defaults import default_space
from adarl.runtime.config import EXPERIMENTS_DIR, TUNE_DIR, list_recipes, load_recipe, recipes_dir, validate_recipe
from adarl.runtime.config.loader import follow_option_overrides

__all__ = [
    "SAMPLERS",
    "PRUNERS",
    "Param",
    "Objective",
    "SamplerSpec",
    "PrunerSpec",
    "TuneSpec",
    "load_tune_spec",
    "resolve_space",
    "tune_target",
    "shipped_tune_specs",
    "check_space",
    "override_value",
    "trial_overrides",
    "grid_values",
]

SAMPLERS = ("tpe", "random", "grid")
PRUNERS = ("median", "none")
_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-+")

Choice = bool | int | float | str | None


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Param(_Model):
    """One recipe key of the search space: a float or int range (``log`` scale, ``step``), or ``choices``."""

    type: Literal["float", "int", "categorical"]
    low: float | None = Field(None, description="Lowest value (float and int).")
    high: float | None = Field(None, description="Highest value (float and int).")
    log: bool = Field(False, description="Sample on a log scale (low must be > 0).")
    step: float | None = Field(None, description="Grid step (float, int; int default 1); not with log for floats.")
    choices: list[Choice] | None = Field(None, description="The values of a categorical key.")

    @model_validator(mode="after")
    def _check(self) -> Param:
        if self.type == "categorical":
            if not self.choices:
                raise ValueError("a categorical key needs a non-empty `choices` list")
            if self.low is not None or self.high is not None or self.log or self.step is not None:
                raise ValueError("a categorical key takes `choices` only (no low, high, log, step)")
            if len({repr(c) for c in self.choices}) != len(self.choices):
                raise ValueError(f"choices must be distinct, got {self.choices}")
            return self
        if self.choices is not None:
            raise ValueError(f"`choices` is for categorical keys; a {self.type} key takes low and high")
        if self.low is None or self.high is None:
            raise ValueError(f"a {self.type} key needs `low` and `high`")
        if self.low > self.high:
            raise ValueError(f"low ({self.low:g}) > high ({self.high:g})")
        if self.log and self.low <= 0:
            raise ValueError(f"log scale needs low > 0, got low = {self.low:g}")
        if self.type == "int":
            for what, v in (("low", self.low), ("high", self.high), ("step", self.step)):
                if v is not None and float(v) != int(v):
                    raise ValueError(f"an int key needs an integer {what}, got {v:g}")
            if self.log and self.step not in (None, 1):
                raise ValueError("an int key on a log scale takes no step (Optuna's rule)")
        elif self.log and self.step is not None:
            raise ValueError("a float key takes either log or step, not both (Optuna's rule)")
        if self.step is not None:
            if self.step <= 0:
                raise ValueError(f"step must be > 0, got {self.step:g}")
            n = (self.high - self.low) / self.step
            if abs(n - round(n)) > 1e-9 * max(1.0, abs(n)):
                raise ValueError(f"high - low ({self.high - self.low:g}) must be a multiple of step ({self.step:g})")
        return self

    def ends(self) -> list[Choice]:
        """The values the recipe must accept: both ends of a range, every choice."""
        if self.type == "categorical":
            return list(self.choices or [])
        if self.type == "int":
            return [int(self.low), int(self.high)]
        return [float(self.low), float(self.high)]


class Objective(_Model):
    """What a trial scores: ``score`` (the mean of its last ``score_last`` nominal evaluations, as the experiment
    reports define a run's score) or ``sweep_worst`` (the worst case of a robustness sweep of the finished run)."""

    metric: Literal["score", "sweep_worst"] = "score"
    score_last: Annotated[int, Field(ge=1)] = Field(
        1, description="A trial's score: the mean of its last N nominal evaluations (also what pruning sees)."
    )
    sweep: SweepSpec | None = Field(None, description="sweep_worst: the sweep run on each finished trial.")
    worst: Literal["worst_mean", "worst_case"] = Field(
        "worst_mean",
        description="sweep_worst: the lowest per-point mean (worst_mean) or the lowest single episode (worst_case).",
    )

    @model_validator(mode="after")
    def _check(self) -> Objective:
        if self.metric == "sweep_worst" and self.sweep is None:
            raise ValueError("metric sweep_worst needs `sweep: {params: ['param=lo:hi:n'], episodes: N}`")
        if self.metric == "score" and self.sweep is not None:
            raise ValueError("`sweep` is for metric sweep_worst; metric score reads the nominal evaluations")
        return self


class SamplerSpec(_Model):
    """Optuna's sampler: ``tpe`` (default), ``random`` or ``grid`` (every key a finite grid), seeded."""

    name: Literal["tpe", "random", "grid"] = "tpe"
    seed: int = 0
    n_startup_trials: Annotated[int, Field(ge=0)] | None = Field(
        None, description="tpe: random trials before TPE starts modelling (default: Optuna's, 10)."
    )


class PrunerSpec(_Model):
    """Optuna's pruner on the intermediate nominal evaluations: ``median`` or ``none``."""

    name: Literal["median", "none"] = "median"
    n_startup_trials: Annotated[int, Field(ge=0)] = Field(
        2, description="median: trials that finish before any is pruned."
    )
    n_warmup_steps: Annotated[int, Field(ge=0)] = Field(
        0, description="median: frames a trial trains before it may be pruned."
    )


_TRIAL_SETS = (
    "each trial sets it itself (its seed from the spec's `seed` or `seeds`, its run folder under the output folder), "
    "after the space's point, so a value given here would be recorded but never trained with; give the trials' seeds "
    "with `seeds: [...]` (the trial's value is the mean over them)"
)


class TuneSpec(_Model):
    """A hyperparameter search: ``n_trials`` runs of ``recipe`` + ``overrides`` + a point of ``space``."""

    kind: Literal["tune"] = Field(description="Marks the file as a tune spec.")
    name: str
    description: str = ""
    recipe: str = Field(description="Base recipe (a name, or a .yaml path relative to the spec's folder).")
    overrides: list[str] = Field(default_factory=list, description="Overrides for every trial (e.g. a small budget).")
    seed: int = Field(0, description="The seed of every trial (one run per trial).")
    seeds: list[int] | None = Field(
        None,
        description="Several seeds per trial instead of `seed`: one run each, at the same time; the trial's value "
        "(and what the pruner sees) is the mean over seeds.",
    )
    space: dict[str, Param] = Field(
        default_factory=dict,
        description="Recipe key -> range or choices; `default` (or no space): the default space of the recipe's "
        "algorithm and rank rule (resolve_space).",
    )
    objective: Objective = Field(default_factory=Objective)
    direction: Literal["maximize", "minimize"] = "maximize"
    n_trials: Annotated[int, Field(ge=1)]
    sampler: SamplerSpec = Field(default_factory=SamplerSpec)
    pruner: PrunerSpec = Field(default_factory=PrunerSpec)
    workers: Annotated[int, Field(ge=1)] = Field(1, description="Trials at a time (each in its own process).")
    output: str | None = Field(None, description="Output folder (default: runs/tune/<name>).")
    #: what the space is made of when it is a default one (resolve_space), for the log line and the report
    _space_from: str = PrivateAttr("")

    @field_validator("space", mode="before")
    @classmethod
    def _default_space(cls, v: Any) -> Any:
        if v is None or v == "default":
            return {}  # resolved against the recipe by resolve_space
        if isinstance(v, str):
            raise ValueError("space must be a mapping of recipe keys, or `default`")
        if isinstance(v, dict) and not v:
            raise ValueError("space is empty: give recipe keys with their ranges, or `default`")
        return v

    @model_validator(mode="after")
    def _check(self) -> TuneSpec:
        if not self.name or not set(self.name) <= _NAME_CHARS or set(self.name) == {"."}:
            raise ValueError(  # it names the default output folder: `..` would be the folder above
                f"name may use letters, digits and . _ - + only and must be a folder name (not . or ..), "
                f"got {self.name!r}"
            )
        if self.seeds is not None:
            if "seed" in self.model_fields_set:
                raise ValueError("give `seed` (one run per trial) or `seeds` (one run per seed), not both")
            if not self.seeds:
                raise ValueError("`seeds` needs at least one seed")
            if len(set(self.seeds)) != len(self.seeds):
                raise ValueError(f"seeds must be distinct, got {self.seeds}")
        for key in self.space:
            if run_own_key(key):  # each trial sets it itself (trial_overrides: its seed, its run's -o)
                raise ValueError(f"space {key!r}: {_TRIAL_SETS}")
        for override in self.overrides:
            if run_own_key(override):
                raise ValueError(f"override {override!r}: {_TRIAL_SETS}")
            key = override.split("=", 1)[0].strip()
            if any(key == k or k.startswith(key + ".") for k in self.space):
                raise ValueError(  # the trial's point comes after the overrides: the override would never train
                    f"override {override!r} sets a key of the search space, which each trial sets after the "
                    "overrides; drop it from the overrides, or the key from the space"
                )
        if self.sampler.name == "grid":
            bad = [k for k, p in self.space.items() if p.type == "float" and p.step is None]
            if bad:
                raise ValueError(f"the grid sampler needs a finite grid: give float key(s) {bad} a `step`")
        return self

    @property
    def trial_seeds(self) -> list[int]:
        """The seeds of each trial: ``seeds``, else ``[seed]``."""
        return list(self.seeds) if self.seeds is not None else [self.seed]


def _field_names(model: type[BaseModel], loc: tuple) -> list[str]:
    """The keys allowed where ``loc`` points (for a did-you-mean on a misspelt key)."""
    fields = {
        (): TuneSpec,
        ("objective",): Objective,
        ("sampler",): SamplerSpec,
        ("pruner",): PrunerSpec,
        ("objective", "sweep"): SweepSpec,
    }
    if len(loc) == 2 and loc[0] == "space":
        return list(Param.model_fields)
    target = fields.get(tuple(loc))
    return list(target.model_fields) if target is not None else []


def _format_validation(err: ValidationError, label: str) -> str:
    lines = []
    for e in err.errors():
        loc = tuple(e["loc"])
        where = ".".join(str(p) for p in loc) or "(top level)"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            allowed = _field_names(TuneSpec, loc[:-1])
            msg = f"unknown key; allowed: {', '.join(allowed)}{did_you_mean(str(loc[-1]), allowed)}"
            lines.append(f"  {where}: {msg}")
            continue
        given = e.get("input")
        shown = "" if isinstance(given, dict) else f" (got {given!r})"
        lines.append(f"  {where}: {msg}{shown}")
    return f"tune spec {label} is invalid (nothing was run):\n" + "\n".join(lines)


def shipped_tune_specs() -> list[str]:
    """The names of the tune specs in the recipe folders (``adarl recipes`` lists them)."""
    return sorted({f.stem for d in recipes_dir() for f in (d / TUNE_DIR).glob("*.yaml")})


def _find(name: str) -> Path:
    p = Path(name)
    if p.is_file():
        return p
    if not name.endswith((".yaml", ".yml")) and "/" not in name and "\\" not in name:
        for d in recipes_dir():
            candidate = d / TUNE_DIR / f"{name}.yaml"
            if candidate.is_file():
                return candidate
    raise RecipeError(
        f"tune spec {name!r} not found{did_you_mean(name, shipped_tune_specs())} (a .yaml path, or a shipped spec "
        f"name: {', '.join(shipped_tune_specs())}; `adarl recipes` lists them)"
    )


def load_tune_spec(path: str | os.PathLike) -> TuneSpec:
    """Read and validate a tune spec's own keys; :class:`RecipeError` names every bad one. See :func:`check_space`."""
    p = _find(str(path))
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as err:
        raise RecipeError(f"tune spec {str(p)!r} is not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise RecipeError(f"tune spec {str(p)!r} must be a mapping, got {type(data).__name__}")
    if data.get("kind") != "tune":
        raise RecipeError(f"{str(p)!r} is not a tune spec (it needs `kind: tune`)")
    try:
        spec = TuneSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(_format_validation(err, repr(str(p)))) from None
    recipe = Path(spec.recipe).expanduser()
    if spec.recipe.endswith((".yaml", ".yml")) and not recipe.is_absolute():  # read from the spec's folder
        beside = (p.parent / recipe).resolve()
        if not beside.is_file():
            raise RecipeError(
                f"tune spec {str(p)!r}: recipe {spec.recipe!r} not found: no file {str(beside)!r} (a relative recipe "
                f"path is read from the spec's folder)"
            )
        spec = spec.model_copy(update={"recipe": str(beside)})
    return resolve_space(spec)


def resolve_space(spec: TuneSpec, recipe=None) -> TuneSpec:
    """The spec itself when its space is given; else the spec with the default space of its recipe (built with the
    spec's overrides: its algorithm's keys, the rank rule's when it adapts ranks, less the keys the overrides set;
    :func:`adarl.experiments.tune._defaults.default_space`), validated as a written space is."""
    if spec.space:
        return spec
    if recipe is None:  # else: the caller's, loaded with the same overrides
        recipe = load_recipe(spec.recipe, [*spec.overrides, f"seed={spec.trial_seeds[0]}"])
    space, what = default_space(recipe, spec.overrides)
    data = spec.model_dump()
    data["space"] = space
    if spec.seeds is not None:
        data.pop("seed")
    try:
        out = TuneSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(_format_validation(err, f"{spec.name!r} (with {what})")) from None
    out._space_from = what
    return out


def _recipe_name(target: str) -> str:
    """A study name for a recipe: its file's stem, or its name with ``/`` as ``-`` (``baselines-hopper_td3``)."""
    stem = Path(target).stem if target.endswith((".yaml", ".yml")) else target.replace("/", "-").replace("\\", "-")
    name = "".join(c if c in _NAME_CHARS else "_" for c in stem).strip(".")
    return name or "recipe"


def tune_target(target: str | os.PathLike, overrides: list[str] = (), n_trials: int | None = None) -> TuneSpec:
    """What ``adarl tune TARGET`` searches: a tune spec (a ``kind: tune`` file, or a shipped spec name: spec names
    come first), else a recipe (a name or a path) searched over its default space (:func:`resolve_space`) with
    rl-zoo's study defaults (TPE, median pruner after a third of the budget, 20 trials). ``overrides`` go after the
    spec's (every trial's recipe), ``n_trials`` replaces its budget."""
    text = os.fspath(target)
    overrides, shipped = list(overrides), shipped_tune_specs()
    is_spec = text in shipped or (Path(text).is_file() and _kind(Path(text)) == "tune")
    if text.endswith((".yaml", ".yml")) and not Path(text).is_file():
        raise RecipeError(f"no file {text!r} (`adarl tune` takes a tune spec or a recipe: a name, or a .yaml path)")
    if is_spec:
        spec = load_tune_spec(text)
        if overrides or n_trials is not None:
            data = spec.model_dump()
            data["overrides"] = [*spec.overrides, *overrides]
            data["n_trials"] = n_trials if n_trials is not None else spec.n_trials
            if spec.seeds is not None:
                data.pop("seed")
            if spec._space_from:
                data["space"] = "default"  # derived again, with the overrides
            try:
                spec = TuneSpec.model_validate(data)
            except ValidationError as err:
                raise RecipeError(_format_validation(err, repr(text))) from None
            spec = resolve_space(spec)
        return spec
    kind = _kind(Path(text)) if Path(text).is_file() else None
    if kind is None and text in _experiment_names():
        kind = "experiment"
    if kind not in (None, "tune"):
        raise RecipeError(
            f"{text!r} is {'an' if kind[:1] in 'aeiou' else 'a'} {kind} spec, not a tune spec or a recipe"
            + (f" (run it with `adarl experiment {text}`)" if kind == "experiment" else "")
        )
    try:
        recipe = load_recipe(text, [*overrides, "seed=0"])
    except RecipeError:
        if Path(text).is_file() or any((d / f"{text}.yaml").is_file() for d in recipes_dir()):
            raise  # a recipe with a bad override or key: its own error
        names = shipped + [n for n, _ in list_recipes()]
        raise RecipeError(
            f"no tune spec or recipe named {text!r}{did_you_mean(text, names)} (`adarl tune` takes a tune spec: a "
            f"kind: tune file or a shipped name, {', '.join(shipped) or 'none'}; or a recipe: a name or a .yaml "
            "path; `adarl recipes` lists both)"
        ) from None
    data = {
        "kind": "tune",
        "name": _recipe_name(text),
        "description": f"adarl tune {text}: the default search space of its algorithm",
        "recipe": str(Path(text).resolve()) if text.endswith((".yaml", ".yml")) else text,
        "overrides": overrides,
        "n_trials": n_trials if n_trials is not None else 20,
        "sampler": {"name": "tpe", "seed": 0, "n_startup_trials": 10},
        "pruner": {"name": "median", "n_startup_trials": 5, "n_warmup_steps": recipe.collector.total_frames // 3},
    }
    try:
        spec = TuneSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(_format_validation(err, f"made of the recipe {text!r}")) from None
    return resolve_space(spec, recipe)


def _experiment_names() -> set[str]:
    return {f.stem for d in recipes_dir() for f in (d / EXPERIMENTS_DIR).glob("*.yaml")}


def _kind(path: Path) -> str | None:
    """A YAML file's ``kind`` (None: none, or not a mapping: a recipe has none)."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    return str(data.get("kind")) if isinstance(data, dict) and data.get("kind") is not None else None


def override_value(value: Choice) -> str:
    """A value as the right-hand side of a ``key=value`` recipe override."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        text = repr(value)
        return text if ("." in text or "e" not in text) else text.replace("e", ".0e", 1)  # YAML: 1.0e-05
    return str(value)


def trial_overrides(spec: TuneSpec, params: dict[str, Any], seed: int | None = None) -> list[str]:
    """The overrides of one run of a trial: the spec's, then its point of the search space, then the seed
    (default: the trial's first seed)."""
    seed = spec.trial_seeds[0] if seed is None else seed
    return [*spec.overrides, *(f"{k}={override_value(v)}" for k, v in params.items()), f"seed={seed}"]


def check_space(spec: TuneSpec) -> int:
    """Check the base recipe and every search-space key against the recipe schema, before any trial runs.

    Each key must be a recipe key, and each end of its range (each choice) must validate as its value: the recipe is
    built with it. Raises :class:`RecipeError` naming the key (with the recipe's did-you-mean or allowed values).
    Returns the base recipe's frame budget."""
    base = load_recipe(spec.recipe, [*spec.overrides, f"seed={spec.trial_seeds[0]}"])
    resolved = base.model_dump(mode="json")
    problems = []
    for key, param in spec.space.items():
        for i, value in enumerate(param.ends()):
            try:
                if i == 0 or not _check_in(resolved, key, value, spec.recipe):
                    load_recipe(spec.recipe, [*spec.overrides, f"{key}={override_value(value)}"])
            except RecipeError as err:
                problems.append(f"  space {key!r} = {value!r}: {str(err).splitlines()[0]}")
                break
    if spec.objective.sweep is not None:
        allowed = parameters_for(base.env.id, base.env.declared())  # a plain gymnasium env: the declared ones
        for text in spec.objective.sweep.params:
            try:
                name, _ = parse_sweep(text)
            except ValueError as err:
                problems.append(f"  objective.sweep: {err}")
                continue
            if name not in allowed:
                problems.append(
                    f"  objective.sweep: {base.env.id} has no parameter {name!r}; allowed: "
                    f"{', '.join(allowed)}{did_you_mean(name, allowed)}"
                )
    if problems:
        raise RecipeError(
            f"tune spec {spec.name!r}: the search space does not validate (nothing was run):\n" + "\n".join(problems)
        )
    return base.collector.total_frames


def _check_in(resolved: dict, key: str, value: Choice, recipe: str) -> bool:
    """Validate ``key = value`` in the resolved base recipe (a copy), without reading its files again: the later
    ends of a key whose first end went through :func:`load_recipe` (which checked the key itself). False: the key is
    not a plain one of the resolved recipe (load it instead)."""
    parts = key.split(".")
    node = resolved
    for part in parts[:-1]:
        node = node.get(part) if isinstance(node, dict) else None
    if not isinstance(node, dict) or parts[-1] not in node or isinstance(node[parts[-1]], (dict, list)):
        return False
    data = copy.deepcopy(resolved)
    target = data
    for part in parts[:-1]:
        target = target[part]
    target[parts[-1]] = value
    follow_option_overrides(data, [f"{key}={override_value(value)}"])  # as load_recipe does with the override
    validate_recipe(data, label=f"{recipe!r} with {key}={override_value(value)}")
    return True


def grid_values(param: Param) -> list[Choice]:
    """Every value of a key on the grid sampler's grid."""
    if param.type == "categorical":
        return list(param.choices or [])
    step = param.step if param.step is not None else 1
    n = int(round((param.high - param.low) / step))
    if param.type == "int":
        return [int(param.low) + i * int(step) for i in range(n + 1)]
    return [float(param.low + i * step) for i in range(n + 1)] if not math.isclose(step, 0) else [param.low]
