"""Experiment specs: many runs (axes x seeds) from one YAML file, and the runs they plan.

A spec names a base ``recipe`` and ``axes``; every combination of axis values times every seed is one run, whose
recipe and overrides are templates filled with the axis values (``"{env}_adarl"``, ``"network.actor.rank={rank}"``).
An axis value is a scalar or ``{name, recipe?, overrides?, seeds?}``. ``budgets`` name smaller (or larger) versions of
the same experiment: other seeds, extra overrides, fewer grid values. Example (``recipes/experiments/``)::

    name: table2
    recipe: "{env}_adarl"
    seeds: [0, 1, 2, 3, 4]
    axes:
      env: [hopper, walker2d]
      variant:
        - {name: actor, overrides: [rank.scope=actor]}
        - {name: both, overrides: [rank.scope=both]}
    budgets:
      small: {seeds: [0, 1], overrides: [collector.total_frames=20000]}

:func:`load_experiment` reads and validates a spec; :func:`plan_runs` lists its runs (:class:`PlannedRun`), which
:mod:`adarl.experiments.execute` runs and :mod:`adarl.experiments.orchestrate` schedules.
"""

from __future__ import annotations

import itertools
import os
import string
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from adarl.errors import AdaRLWarning, RecipeError, did_you_mean, one_of
from adarl.experiments._paper_spec import PaperTable
from adarl.runtime.config import EXPERIMENTS_DIR, recipes_dir
from adarl.runtime.run_folder.results import is_url

__all__ = [
    "AxisValue",
    "SweepSpec",
    "Budget",
    "ReportSpec",
    "ResourcesSpec",
    "ExperimentSpec",
    "PlannedRun",
    "load_experiment",
    "shipped_experiments",
    "resolve_budget",
    "default_output",
    "unused_axes",
    "plan_runs",
]

_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-+")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class AxisValue(_Model):
    """One value of an axis: its name (in run ids, tables and templates), and what it changes."""

    name: str = Field(description="Label of the value; `{axis}` in templates becomes it.")
    recipe: str | None = Field(None, description="Recipe template for runs with this value (overrides the spec's).")
    overrides: list[str] = Field(default_factory=list, description="Recipe overrides (templates) this value adds.")
    seeds: list[int] | None = Field(
        None,
        description="The only seeds runs with this value use, within the budget's (e.g. a costly control at 5 "
        "seeds beside arms at 8); default: every seed of the budget.",
    )

    @field_validator("name")
    @classmethod
    def _check_name(cls, v: str) -> str:
        if not v or not set(v) <= _NAME_CHARS:
            raise ValueError(f"axis value names may use letters, digits and . _ - + only, got {v!r}")
        return v


def _as_axis_value(v: Any) -> Any:
    if isinstance(v, bool) or v is None:
        raise ValueError(
            f"an axis value must be a number, a string or a mapping {{name, recipe, overrides, seeds}}, got {v!r}"
        )
    if isinstance(v, (int, float, str)):
        return {"name": str(v)}
    return v


class SweepSpec(_Model):
    """A robustness sweep to run on every finished run (see :mod:`adarl.experiments.sweep`)."""

    params: list[str] = Field(
        description="One or two grid specs 'param=lo:hi:n' (others held at nominal).", min_length=1, max_length=2
    )
    episodes: Annotated[int, Field(ge=1)] = Field(5, description="Episodes per grid point.")
    name: str | None = Field(None, description="File stem under sweeps/ (default: the parameter names).")


class Budget(_Model):
    """A named size of the experiment (e.g. ``small``: finishes on 2 CPU cores in under an hour)."""

    description: str = ""
    seeds: list[int] | None = Field(None, description="Seeds for this budget (default: the spec's).")
    overrides: list[str] = Field(default_factory=list, description="Overrides added to every run.")
    axes: dict[str, list[str]] = Field(
        default_factory=dict, description="Keep only these value names of an axis, e.g. {rank: ['1', '4']}."
    )
    sweeps: list[SweepSpec] | None = Field(
        None, description="Robustness sweeps for this budget (default: the spec's); [] runs none."
    )
    value_seeds: dict[str, dict[str, list[int] | None]] = Field(
        default_factory=dict,
        description="Per axis and value name, the seeds that value runs at in this budget, replacing the value's own "
        "`seeds` (null: every seed of the budget), e.g. {algorithm: {parseval: null}} where a control that a smaller "
        "budget runs at 5 seeds runs at all 8.",
    )
    value_overrides: dict[str, dict[str, list[str]]] = Field(
        default_factory=dict,
        description="Per axis and value name, overrides (templates) the runs with that value get in this budget, "
        "after the value's and the budget's own, e.g. {algorithm: {parseval: ['algorithm.parseval.lam=1.0e-4']}} "
        "where one env's row runs a baseline at the value selected on that env.",
    )

    @field_validator("axes", mode="before")
    @classmethod
    def _stringify(cls, v: Any) -> Any:
        if isinstance(v, dict):
            return {k: [str(x) for x in vals] if isinstance(vals, list) else vals for k, vals in v.items()}
        return v


class ReportSpec(_Model):
    """How the aggregate report lays out the runs."""

    columns: str | None = Field(None, description="Axis shown as table columns (default: 'algorithm' if present).")
    x_axis: str | None = Field(None, description="Numeric axis for a return-vs-value plot (e.g. 'rank', Fig. 1).")
    intrinsic_rank: int | None = Field(None, description="Reference line in rank plots (default: 2*d_a+1 of the env).")
    reference: str | None = Field(
        None,
        description="A value of the column axis (e.g. 'adarl'): the statistics table "
        "gives the probability that it improves on each other column.",
    )
    event_window: Annotated[int, Field(ge=1)] | None = Field(
        None,
        description="Frames before and after each rank event over which the report compares the training "
        "episode return (the transient dip after a truncation, Fig. 9).",
    )
    at_updates: list[Annotated[int, Field(ge=1)]] = Field(
        default_factory=list,
        description="Optimisation steps at which to report each run's score as well (e.g. the "
        "ends of the paper's iterations 1, 3 and 5 in Table 2): the first evaluation at or after each.",
    )
    pairs: list[tuple[str, str]] = Field(
        default_factory=list,
        description="Further comparisons between two values of the column axis, [a, b]: the report gives P(a > b) "
        "with its interval and the decision rule's verdict (e.g. [sac_restarts, sac_full]: what the restarts alone "
        "do), beside P(reference > each value).",
    )
    score_last: Annotated[int, Field(ge=1)] = Field(
        1,
        description="A run's score is the mean of its last `score_last` nominal evaluations (issue 34's protocol: 3; "
        "1 = the last evaluation alone).",
    )
    plateau: (
        Annotated[float, Field(allow_inf_nan=False)] | dict[str, Annotated[float, Field(allow_inf_nan=False)]] | None
    ) = Field(
        None,
        description="A return threshold: the report counts, per setting, the seeds whose best nominal evaluation "
        "exceeds it (Hopper's stand-still plateau: 1500 in issue 34's protocol). One for every setting, or one per "
        "value of an axis (`{hopper: 1500, humanoid: 5500}`: each env's stand-still return + 500; every value of "
        "that axis named).",
    )
    verdict_seeds: Annotated[int, Field(ge=2)] | dict[str, Annotated[int, Field(ge=2)]] | None = Field(
        None,
        description="The seed count a protocol planned: the decision rule gives a verdict only when both sides have "
        "at least this many seeds; before, the report shows P with its interval as an interim estimate and says the "
        "verdict waits (runs that land one by one are never read as a decision). One count for every arm, or one "
        "per value of the column axis (`{adarl: 8, fixed_final: 5}`: every arm of the runs must be named).",
    )

    paper_table: PaperTable | None = Field(
        None,
        description="A table the paper prints (e.g. Table 1: per env and method its mean and std), shown beside ours "
        "with both bold rules and P(reference > each method) per row; with `normalise`, the aggregate across its rows "
        "(normalised scores, IQM, optimality gap, performance profile). Keys: title, source, rows, columns, labels, "
        "extra_columns, values, normalise {random, random_from, reference}.",
    )
    formats: list[Literal["png", "pdf", "svg"]] = Field(
        default_factory=lambda: ["png", "pdf", "svg"],
        description="Files each report figure is written as, side by side under one name: PNG (which report.md "
        "links; always among them), PDF and SVG (vector, for a paper).",
    )

    @field_validator("formats")
    @classmethod
    def _formats_include_png(cls, formats: list[str]) -> list[str]:
        if "png" not in formats or len(set(formats)) != len(formats):
            raise ValueError("distinct values of png, pdf, svg with png among them (the report links the PNG)")
        return formats

    @field_validator("pairs")
    @classmethod
    def _pairs_compare_two_values(cls, pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
        for a, b in pairs:
            if a == b:
                raise ValueError(f"a pair compares two different values, got [{a!r}, {b!r}]")
        return pairs


class ResourcesSpec(_Model):
    """What one run needs, for the ``ray`` and ``submitit`` launchers (the local launcher uses ``workers``)."""

    cpus_per_run: Annotated[float, Field(gt=0)] = Field(1, description="CPUs per run (also its torch threads).")
    gpus_per_run: Annotated[float, Field(ge=0)] = Field(0, description="GPUs per run (Ray may take fractions).")
    timeout_min: Annotated[int, Field(ge=1)] = Field(
        24 * 60, description="SLURM time limit per job (minutes); a job that hits it is requeued from its checkpoint."
    )
    slurm_partition: str | None = Field(None, description="SLURM partition (default: the cluster's).")
    slurm_additional_parameters: dict[str, Any] = Field(
        default_factory=dict, description="Extra sbatch parameters, e.g. {account: x}."
    )


def run_own_key(override: str) -> str | None:
    """The recipe key of ``override`` (``key=value``, or a bare key) when it is one each run sets itself after every
    override (its ``seed``, its ``output`` folder): an experiment's and a tune study's spec refuse it (issue 46)."""
    key = override.split("=", 1)[0].strip().lstrip("+~")
    return key if key in ("seed", "output") or key.startswith("output.") else None


def _refuse_run_own_keys(spec: ExperimentSpec) -> None:
    """An override of a key each run sets itself (``seed`` from ``seeds``, ``output`` from the run's folder) would be
    recorded in the spec yet overridden by the run's own, appended last: refused by name (issue 46)."""
    places = [("overrides", o) for o in spec.overrides]
    places += [
        (f"axis {a!r} value {v.name!r} overrides", o)
        for a, vals in spec.axes.items()
        for v in vals
        for o in v.overrides
    ]
    places += [(f"budget {b!r} overrides", o) for b, budget in spec.budgets.items() for o in budget.overrides]
    for where, override in places:
        if key := run_own_key(override):
            raise ValueError(
                f"{where}: {override!r} sets {key!r}, which each run sets itself (its seed from the spec's `seeds`, "
                f"a budget's `seeds` or a value's `seeds`; its folder under the experiment's output), after these "
                f"overrides: give the seeds with `seeds: [...]` instead"
            )


class ExperimentSpec(_Model):
    """A multi-run experiment: ``recipe`` x ``axes`` x ``seeds``."""

    kind: Literal["experiment"] = Field(description="Marks the file as an experiment spec (not a recipe).")
    name: str
    description: str = ""
    recipe: str | None = Field(None, description="Recipe template (name or path), e.g. '{env}_adarl'.")
    overrides: list[str] = Field(default_factory=list, description="Overrides (templates) for every run.")
    axes: dict[str, list[AxisValue]] = Field(default_factory=dict)
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1)
    budgets: dict[str, Budget] = Field(default_factory=dict)
    default_budget: str | None = Field(None, description="Budget used when none is asked for (default: none).")
    output: str | None = Field(
        None,
        description="Output folder or fsspec URL, e.g. s3://bucket/exp (default: runs/experiments/<name>[-<budget>]).",
    )
    workers: Annotated[int, Field(ge=1)] = Field(1, description="Runs at a time (each in its own process).")
    pack: Annotated[int, Field(ge=1)] = Field(
        1,
        description="Seeds of one arm trained side by side in one process, their SAC updates one batched program "
        "(adarl.experiments.packing; local launcher). 1: each run in its own process.",
    )
    resources: ResourcesSpec = Field(default_factory=ResourcesSpec)
    sweeps: list[SweepSpec] = Field(default_factory=list)
    report: ReportSpec = Field(default_factory=ReportSpec)

    @field_validator("axes", mode="before")
    @classmethod
    def _axis_values(cls, v: Any) -> Any:
        if not isinstance(v, dict):
            return v
        out = {}
        for axis, values in v.items():
            if not isinstance(values, list) or not values:
                raise ValueError(f"axis {axis!r} must be a non-empty list of values, got {values!r}")
            out[axis] = [_as_axis_value(x) for x in values]
        return out

    @field_validator("seeds")
    @classmethod
    def _unique_seeds(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"seeds must be distinct, got {v}")
        return v

    @model_validator(mode="after")
    def _check(self) -> ExperimentSpec:
        if not self.name or not set(self.name) <= _NAME_CHARS or set(self.name) == {"."}:
            raise ValueError(  # it names the default output folder: `..` would be the folder above
                f"name may use letters, digits and . _ - + only and must be a folder name (not . or ..), "
                f"got {self.name!r}"
            )
        _refuse_run_own_keys(self)
        for axis, values in self.axes.items():
            if not axis.isidentifier() or axis == "seed":
                raise ValueError(f"axis name {axis!r} must be an identifier other than 'seed'")
            names = [v.name for v in values]
            if len(set(names)) != len(names):
                raise ValueError(f"axis {axis!r} has repeated value names {names}")
        if self.recipe is None:
            missing = [a for a, vals in self.axes.items() if not all(v.recipe for v in vals)]
            if not any(all(v.recipe for v in vals) for vals in self.axes.values()):
                raise ValueError(
                    "no recipe: set `recipe`, or a `recipe` on every value of one axis "
                    f"(axes without one on every value: {missing})"
                )
        for bname, budget in self.budgets.items():
            for axis, keep in budget.axes.items():
                if axis not in self.axes:
                    raise ValueError(f"budget {bname!r} restricts unknown axis {axis!r}; axes: {list(self.axes)}")
                known = [v.name for v in self.axes[axis]]
                unknown = [k for k in keep if k not in known]
                if unknown:
                    raise ValueError(f"budget {bname!r}: axis {axis!r} has no value(s) {unknown}; values: {known}")
            for field, given in (("value_seeds", budget.value_seeds), ("value_overrides", budget.value_overrides)):
                for axis, per_value in given.items():
                    if axis not in self.axes:
                        raise ValueError(
                            f"budget {bname!r}: {field} names unknown axis {axis!r}; axes: {list(self.axes)}"
                        )
                    known = [v.name for v in self.axes[axis]]
                    unknown = [k for k in per_value if k not in known]
                    if unknown:
                        raise ValueError(
                            f"budget {bname!r}: {field} of axis {axis!r} names no value(s) {unknown}; values: {known}"
                        )
        if self.default_budget is not None and self.default_budget not in self.budgets:
            raise ValueError(f"default_budget {self.default_budget!r} is not one of the budgets {list(self.budgets)}")
        for where, axis in (("report.columns", self.report.columns), ("report.x_axis", self.report.x_axis)):
            if axis is not None and axis not in self.axes:
                raise ValueError(f"{where} {axis!r} is not an axis; axes: {list(self.axes)}")
        col = self.report.columns or ("algorithm" if "algorithm" in self.axes else None)
        known = [v.name for v in self.axes.get(col, [])] if col else []  # the column axis's values
        if self.report.reference is not None:
            if self.report.reference not in known:
                raise ValueError(
                    f"report.reference {self.report.reference!r} must be a value of the column axis {col!r}: {known}"
                )
        unknown = sorted({v for pair in self.report.pairs for v in pair if v not in known})
        if unknown:
            raise ValueError(f"report.pairs name {unknown}, not values of the column axis {col!r}: {known}")
        if isinstance(self.report.plateau, dict):
            keys = set(self.report.plateau)
            if not any(keys == {v.name for v in vals} for vals in self.axes.values()):
                raise ValueError(
                    f"report.plateau per value must name every value of one axis once, got {sorted(keys)}; axes: "
                    + "; ".join(f"{a}: {[v.name for v in vals]}" for a, vals in self.axes.items())
                )
        need = self.report.verdict_seeds
        if isinstance(need, dict) and col is None:
            raise ValueError(
                f"report.verdict_seeds per arm needs a column axis (report.columns); axes: {list(self.axes)}"
            )
        if isinstance(need, dict) and set(need) != set(known):
            raise ValueError(
                f"report.verdict_seeds per arm must name each value of the column axis {col!r} once: {known} "
                f"(it names {list(need)}); or give one count for all"
            )
        if self.report.paper_table is not None:
            self.report.paper_table.check_axes({a: [v.name for v in vals] for a, vals in self.axes.items()}, col)
        return self


@dataclass
class PlannedRun:
    """One run of an experiment: where it lives and how to start it."""

    run_id: str
    axes: dict[str, str]
    seed: int
    recipe: str
    overrides: list[str]
    path: str
    # pending | finished | skipped-finished | missing-recipe | failed | interrupted | stopped | changed (a dry run's:
    # its folder was made from another recipe, adarl.experiments.orchestrate)
    status: str = "pending"
    message: str = ""
    total_frames: int | None = None  # the recipe's frame budget, known once it validated (progress before it starts)
    wall_time_s: float = 0.0
    scratch: str | None = None  # URL runs: local folder to train in (None: $TMPDIR/adarl-scratch of the worker)
    # the experiment's (or study's) output folder, which holds the run folder: a run never creates it, so one deleted
    # or moved while the experiment runs stops the runs instead of coming back half-filled (None: created as needed)
    output: str | None = None
    pack: str | None = None  # the pack it trained in (adarl experiment --pack; adarl.experiments.packing)

    def as_dict(self) -> dict:
        d = asdict(self)
        del d["output"]  # experiment.json is in it
        for key in ("scratch", "pack"):
            if d[key] is None:
                del d[key]
        return d


def _format_validation(err: ValidationError, label: str) -> str:
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"].removeprefix("Value error, ")
        given = e.get("input")
        shown = "" if isinstance(given, dict) else f" (got {given!r})"
        lines.append(f"  {loc}: {msg}{shown}")
    return f"experiment spec {label} is invalid:\n" + "\n".join(lines)


def load_experiment(path: str | os.PathLike) -> ExperimentSpec:
    """Read and validate an experiment spec; :class:`RecipeError` names every bad key."""
    p = Path(path)
    if not p.is_file():
        p = _find_shipped(str(path))
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as err:
        raise RecipeError(f"experiment spec {str(p)!r} is not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise RecipeError(f"experiment spec {str(p)!r} must be a mapping, got {type(data).__name__}")
    if data.get("kind") != "experiment":
        raise RecipeError(
            f"{str(p)!r} is not an experiment spec (it needs `kind: experiment`); "
            "to train a single recipe use `adarl run`"
        )
    try:
        return ExperimentSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(_format_validation(err, repr(str(p)))) from None


def report_options(pairs: list[str]) -> dict:
    """``KEY=VALUE`` strings (``adarl report --set``) as a mapping of the spec's ``report:`` section, each value read as
    YAML and checked by :class:`ReportSpec` (so that loose run folders can be reported by an experiment's rule, e.g.
    ``score_last=3 plateau=1500``); :class:`RecipeError` names a bad key or value and the allowed ones."""
    options: dict = {}
    allowed = sorted(ReportSpec.model_fields)
    for pair in pairs:
        key, sep, text = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise RecipeError(f"report option {pair!r} must be KEY=VALUE with KEY one of {one_of(allowed)}")
        if key not in ReportSpec.model_fields:
            raise RecipeError(
                f"unknown report option {key!r}{did_you_mean(key, allowed)}; the keys of an experiment spec's "
                f"report section are {one_of(allowed)}"
            )
        try:
            options[key] = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError as err:
            raise RecipeError(f"report option {pair!r}: the value is not valid YAML: {err}") from None
    try:
        checked = ReportSpec.model_validate(options)
    except ValidationError as err:
        detail = _format_validation(err, "").split("\n", 1)[1]
        raise RecipeError(f"report options (adarl report --set) are invalid:\n{detail}") from None
    return {k: _plain(getattr(checked, k)) for k in options}


def _plain(v: Any) -> Any:
    """A checked option as the report reads it: a nested section (``paper_table``) as its mapping."""
    return v.model_dump() if isinstance(v, BaseModel) else v


def shipped_experiments() -> list[str]:
    """Names of the experiment specs in the ``experiments/`` folder of each recipes folder."""
    names = {f.stem for d in recipes_dir() for f in (d / EXPERIMENTS_DIR).glob("*.yaml")}
    return sorted(names)


def _find_shipped(name: str) -> Path:
    if not name.endswith((".yaml", ".yml")) and "/" not in name and "\\" not in name:
        for d in recipes_dir():
            candidate = d / EXPERIMENTS_DIR / f"{name}.yaml"
            if candidate.is_file():
                return candidate
    raise RecipeError(
        f"experiment spec {name!r} not found (a .yaml path, or a shipped spec name: {', '.join(shipped_experiments())})"
    )


def _fill(template: str, values: dict[str, str], where: str) -> str:
    try:
        return template.format(**values)
    except KeyError as err:
        raise RecipeError(
            f"{where}: template {template!r} uses {{{err.args[0]}}}, which is not an axis or 'seed'; "
            f"available: {sorted(values)}"
        ) from None
    except (ValueError, IndexError) as err:
        raise RecipeError(f"{where}: bad template {template!r}: {err}") from None


def resolve_budget(spec: ExperimentSpec, budget: str | None) -> tuple[str | None, Budget]:
    name = budget if budget is not None else spec.default_budget
    if name is None:
        return None, Budget()
    if name not in spec.budgets:
        raise RecipeError(
            f"experiment {spec.name!r} has no budget {name!r}; budgets: {sorted(spec.budgets) or '(none)'}"
        )
    return name, spec.budgets[name]


def default_output(spec: ExperimentSpec, budget: str | None) -> Path | str:
    if spec.output:
        return spec.output if is_url(spec.output) else Path(spec.output)
    return Path("runs") / "experiments" / (spec.name + (f"-{budget}" if budget else ""))


def unused_axes(spec: ExperimentSpec) -> list[str]:
    """Axes that change nothing: no value brings a recipe or overrides and no template names ``{axis}``; their
    values plan identical runs (the same training repeated under other names)."""
    templates = [spec.recipe or "", *spec.overrides, *(o for b in spec.budgets.values() for o in b.overrides)]
    templates += [t for vals in spec.axes.values() for v in vals for t in (v.recipe or "", *v.overrides)]
    named = set()
    for t in templates:
        try:
            named |= {f.split(".")[0].split("[")[0] for _, f, _, _ in string.Formatter().parse(t) if f}
        except ValueError:  # a malformed template is reported when it is filled
            continue
    return [a for a, vals in spec.axes.items() if a not in named and not any(v.recipe or v.overrides for v in vals)]


def plan_runs(spec: ExperimentSpec, output: str | os.PathLike, budget: str | None = None) -> list[PlannedRun]:
    """Every run of the spec under ``budget``: axes product x seeds, recipe and overrides filled in.

    An axis that changes nothing (:func:`unused_axes`) is planned anyway, with an
    :class:`~adarl.errors.AdaRLWarning`: its runs would repeat the same training."""
    for axis in unused_axes(spec):
        names = [v.name for v in spec.axes[axis]]
        warnings.warn(
            f"experiment {spec.name!r}: axis {axis!r} changes nothing (no override or recipe uses "
            f"{{{axis}}} and its values {names} bring none), so its runs repeat the same training; use "
            f"{{{axis}}} in an override, give its values overrides, or remove it",
            AdaRLWarning,
            stacklevel=2,
        )
    _, b = resolve_budget(spec, budget)
    seeds = b.seeds if b.seeds is not None else spec.seeds
    axes = {a: [v for v in vals if a not in b.axes or v.name in b.axes[a]] for a, vals in spec.axes.items()}

    def value_seeds(axis: str, v: AxisValue) -> list[int] | None:  # the budget's value_seeds, else the value's own
        per_value = b.value_seeds.get(axis, {})
        return per_value[v.name] if v.name in per_value else v.seeds

    url = is_url(output)
    out = str(output).rstrip("/") if url else Path(output)
    runs = []
    for combo in itertools.product(*axes.values()) if axes else [()]:
        named = dict(zip(axes, combo))
        for seed in seeds:
            if any((own := value_seeds(a, v)) is not None and seed not in own for a, v in named.items()):
                continue
            values = {a: v.name for a, v in named.items()} | {"seed": str(seed)}
            recipe_t = spec.recipe
            overrides_t = list(spec.overrides)
            for v in named.values():
                if v.recipe:
                    recipe_t = v.recipe
                overrides_t += v.overrides
            overrides_t += b.overrides
            for a, v in named.items():  # the budget's overrides for this value, last: they win
                overrides_t += b.value_overrides.get(a, {}).get(v.name, [])
            run_id = "__".join([f"{a}={v.name}" for a, v in named.items()] + [f"seed={seed}"])
            recipe = _fill(recipe_t, values, f"run {run_id} recipe")
            overrides = [_fill(o, values, f"run {run_id} override") for o in overrides_t] + [f"seed={seed}"]
            runs.append(
                PlannedRun(
                    run_id,
                    {a: v.name for a, v in named.items()},
                    seed,
                    recipe,
                    overrides,
                    f"{out}/{run_id}" if url else str(out / run_id),
                    output=str(out),
                )
            )
    return runs
