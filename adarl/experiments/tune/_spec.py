"""Hyperparameter-search specs (``adarl tune``): a base recipe, a search space over recipe keys, the objective, the
trial budget, the sampler and the pruner; validated in full before any trial runs.

A spec is a YAML file with ``kind: tune`` (the shipped ones are in ``recipes/tune/``)::

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

:func:`load_tune_spec` reads the file and checks its own keys (did-you-mean for a misspelt one, allowed values for a
name); :func:`check_space` checks every search-space key against the recipe: the key must exist and each end of its
range (each choice) must validate as a value of it, by building the recipe with it. Nothing here imports Optuna:
:mod:`adarl.experiments.tune._study` runs the study.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from adarl.envs.registry import env_parameters
from adarl.errors import RecipeError, did_you_mean
from adarl.experiments.spec import SweepSpec, run_own_key
from adarl.experiments.sweep import parse_sweep
from adarl.runtime.config import TUNE_DIR, load_recipe, recipes_dir

__all__ = [
    "SAMPLERS",
    "PRUNERS",
    "Param",
    "Objective",
    "SamplerSpec",
    "PrunerSpec",
    "TuneSpec",
    "load_tune_spec",
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
    space: dict[str, Param] = Field(min_length=1, description="Recipe key -> range or choices.")
    objective: Objective = Field(default_factory=Objective)
    direction: Literal["maximize", "minimize"] = "maximize"
    n_trials: Annotated[int, Field(ge=1)]
    sampler: SamplerSpec = Field(default_factory=SamplerSpec)
    pruner: PrunerSpec = Field(default_factory=PrunerSpec)
    workers: Annotated[int, Field(ge=1)] = Field(1, description="Trials at a time (each in its own process).")
    output: str | None = Field(None, description="Output folder (default: runs/tune/<name>).")

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
        f"tune spec {name!r} not found (a .yaml path, or a shipped spec name: {', '.join(shipped_tune_specs())})"
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
    return spec


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
    problems = []
    for key, param in spec.space.items():
        for value in param.ends():
            try:
                load_recipe(spec.recipe, [*spec.overrides, f"{key}={override_value(value)}"])
            except RecipeError as err:
                problems.append(f"  space {key!r} = {value!r}: {str(err).splitlines()[0]}")
                break
    if spec.objective.sweep is not None:
        allowed = env_parameters(base.env.id)
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


def grid_values(param: Param) -> list[Choice]:
    """Every value of a key on the grid sampler's grid."""
    if param.type == "categorical":
        return list(param.choices or [])
    step = param.step if param.step is not None else 1
    n = int(round((param.high - param.low) / step))
    if param.type == "int":
        return [int(param.low) + i * int(step) for i in range(n + 1)]
    return [float(param.low + i * step) for i in range(n + 1)] if not math.isclose(step, 0) else [param.low]
