"""Experiments: many runs (axes x seeds) from one YAML spec, run locally and resumably, then aggregated.

A spec names a base ``recipe`` and ``axes``; every combination of axis values times every seed is one run, whose
recipe and overrides are templates filled with the axis values (``"{env}_adarl"``, ``"network.actor.rank={rank}"``).
An axis value is a scalar or ``{name, recipe?, overrides?}``. ``budgets`` name smaller (or larger) versions of the
same experiment: other seeds, extra overrides, fewer grid values. Example (``recipes/experiments/``)::

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

:func:`run_experiment` runs each run with the ``adarl`` command in its own folder ``<output>/<run id>`` (one
after another, or ``workers`` at a time), skips finished runs, resumes interrupted ones from their checkpoint, flags
runs whose recipe does not exist (yet), then sweeps each finished run if the spec asks and writes the aggregate
report (:mod:`adarl.aggregate`). ``experiment.json`` in the output folder records what ran.

The output may be an fsspec URL (``s3://bucket/exp``): runs then train in a local scratch folder and are copied to
``<URL>/<run id>`` after each checkpoint (:mod:`adarl.results`); the finished-run check, ``experiment.json``, the
attempt records, the progress board and the report read and write the URL.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from adarl.errors import AdaRLError, AdaRLValueError, AdaRLWarning, RecipeError
from adarl.results import is_url

__all__ = ["ExperimentSpec", "PlannedRun", "load_experiment", "plan_runs", "unused_axes", "run_experiment",
           "run_is_finished",
           "execute_run", "read_attempts", "shipped_experiments", "EXPERIMENT_FILE", "ATTEMPTS_DIR"]

EXPERIMENT_FILE = "experiment.json"
ATTEMPTS_DIR = "attempts"  # <output>/attempts/<run id>.jsonl: one line per start and end of a run, by any launcher
_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-+")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class AxisValue(_Model):
    """One value of an axis: its name (in run ids, tables and templates), and what it changes."""

    name: str = Field(description="Label of the value; `{axis}` in templates becomes it.")
    recipe: str | None = Field(None, description="Recipe template for runs with this value (overrides the spec's).")
    overrides: list[str] = Field(default_factory=list, description="Recipe overrides (templates) this value adds.")

    @field_validator("name")
    @classmethod
    def _check_name(cls, v: str) -> str:
        if not v or not set(v) <= _NAME_CHARS:
            raise ValueError(f"axis value names may use letters, digits and . _ - + only, got {v!r}")
        return v


def _as_axis_value(v: Any) -> Any:
    if isinstance(v, bool) or v is None:
        raise ValueError(f"an axis value must be a number, a string or a mapping {{name, recipe, overrides}}, got {v!r}")
    if isinstance(v, (int, float, str)):
        return {"name": str(v)}
    return v


class SweepSpec(_Model):
    """A robustness sweep to run on every finished run (see :mod:`adarl.sweep`)."""

    params: list[str] = Field(description="One or two grid specs 'param=lo:hi:n' (others held at nominal).",
                              min_length=1, max_length=2)
    episodes: Annotated[int, Field(ge=1)] = Field(5, description="Episodes per grid point.")
    name: str | None = Field(None, description="File stem under sweeps/ (default: the parameter names).")


class Budget(_Model):
    """A named size of the experiment (e.g. ``small``: finishes on 2 CPU cores in under an hour)."""

    description: str = ""
    seeds: list[int] | None = Field(None, description="Seeds for this budget (default: the spec's).")
    overrides: list[str] = Field(default_factory=list, description="Overrides added to every run.")
    axes: dict[str, list[str]] = Field(default_factory=dict,
                                       description="Keep only these value names of an axis, e.g. {rank: ['1', '4']}.")
    sweeps: list[SweepSpec] | None = Field(None, description="Robustness sweeps for this budget (default: the "
                                           "spec's); [] runs none.")

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
    reference: str | None = Field(None, description="A value of the column axis (e.g. 'adarl'): the statistics table "
                                  "gives the probability that it improves on each other column.")
    event_window: Annotated[int, Field(ge=1)] | None = Field(
        None, description="Frames before and after each rank event over which the report compares the training "
        "episode return (the transient dip after a truncation, Fig. 9).")
    at_updates: list[Annotated[int, Field(ge=1)]] = Field(
        default_factory=list, description="Optimisation steps at which to report each run's score as well (e.g. the "
        "ends of the paper's iterations 1, 3 and 5 in Table 2): the first evaluation at or after each.")


class ResourcesSpec(_Model):
    """What one run needs, for the ``ray`` and ``submitit`` launchers (the local launcher uses ``workers``)."""

    cpus_per_run: Annotated[float, Field(gt=0)] = Field(1, description="CPUs per run (also its torch threads).")
    gpus_per_run: Annotated[float, Field(ge=0)] = Field(0, description="GPUs per run (Ray may take fractions).")
    timeout_min: Annotated[int, Field(ge=1)] = Field(24 * 60, description="SLURM time limit per job (minutes); "
                                                     "a job that hits it is requeued from its checkpoint.")
    slurm_partition: str | None = Field(None, description="SLURM partition (default: the cluster's).")
    slurm_additional_parameters: dict[str, Any] = Field(default_factory=dict,
                                                        description="Extra sbatch parameters, e.g. {account: x}.")


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
    output: str | None = Field(None, description="Output folder or fsspec URL, e.g. s3://bucket/exp "
                               "(default: runs/experiments/<name>[-<budget>]).")
    workers: Annotated[int, Field(ge=1)] = Field(1, description="Runs at a time (each in its own process).")
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
        if not self.name or not set(self.name) <= _NAME_CHARS:
            raise ValueError(f"name may use letters, digits and . _ - + only, got {self.name!r}")
        for axis, values in self.axes.items():
            if not axis.isidentifier() or axis == "seed":
                raise ValueError(f"axis name {axis!r} must be an identifier other than 'seed'")
            names = [v.name for v in values]
            if len(set(names)) != len(names):
                raise ValueError(f"axis {axis!r} has repeated value names {names}")
        if self.recipe is None:
            missing = [a for a, vals in self.axes.items() if not all(v.recipe for v in vals)]
            if not any(all(v.recipe for v in vals) for vals in self.axes.values()):
                raise ValueError("no recipe: set `recipe`, or a `recipe` on every value of one axis "
                                 f"(axes without one on every value: {missing})")
        for bname, budget in self.budgets.items():
            for axis, keep in budget.axes.items():
                if axis not in self.axes:
                    raise ValueError(f"budget {bname!r} restricts unknown axis {axis!r}; axes: {list(self.axes)}")
                known = [v.name for v in self.axes[axis]]
                unknown = [k for k in keep if k not in known]
                if unknown:
                    raise ValueError(f"budget {bname!r}: axis {axis!r} has no value(s) {unknown}; values: {known}")
        if self.default_budget is not None and self.default_budget not in self.budgets:
            raise ValueError(f"default_budget {self.default_budget!r} is not one of the budgets {list(self.budgets)}")
        for where, axis in (("report.columns", self.report.columns), ("report.x_axis", self.report.x_axis)):
            if axis is not None and axis not in self.axes:
                raise ValueError(f"{where} {axis!r} is not an axis; axes: {list(self.axes)}")
        if self.report.reference is not None:
            col = self.report.columns or ("algorithm" if "algorithm" in self.axes else None)
            known = [v.name for v in self.axes.get(col, [])] if col else []
            if self.report.reference not in known:
                raise ValueError(f"report.reference {self.report.reference!r} must be a value of the column axis "
                                 f"{col!r}: {known}")
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
    status: str = "pending"  # pending | finished | skipped-finished | missing-recipe | failed
    message: str = ""
    wall_time_s: float = 0.0
    scratch: str | None = None  # URL runs: local folder to train in (None: $TMPDIR/adarl-scratch of the worker)

    def as_dict(self) -> dict:
        d = asdict(self)
        if d["scratch"] is None:
            del d["scratch"]
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
        raise RecipeError(f"{str(p)!r} is not an experiment spec (it needs `kind: experiment`); "
                          "to train a single recipe use `adarl run`")
    try:
        return ExperimentSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(_format_validation(err, repr(str(p)))) from None


def shipped_experiments() -> list[str]:
    """Names of the experiment specs in the ``experiments/`` folder of each recipes folder."""
    from adarl.config import EXPERIMENTS_DIR, recipes_dir

    names = {f.stem for d in recipes_dir() for f in (d / EXPERIMENTS_DIR).glob("*.yaml")}
    return sorted(names)


def _find_shipped(name: str) -> Path:
    from adarl.config import EXPERIMENTS_DIR, recipes_dir

    if not name.endswith((".yaml", ".yml")) and "/" not in name and "\\" not in name:
        for d in recipes_dir():
            candidate = d / EXPERIMENTS_DIR / f"{name}.yaml"
            if candidate.is_file():
                return candidate
    raise RecipeError(f"experiment spec {name!r} not found (a .yaml path, or a shipped spec name: "
                      f"{', '.join(shipped_experiments())})")


def _fill(template: str, values: dict[str, str], where: str) -> str:
    try:
        return template.format(**values)
    except KeyError as err:
        raise RecipeError(f"{where}: template {template!r} uses {{{err.args[0]}}}, which is not an axis or 'seed'; "
                          f"available: {sorted(values)}") from None
    except (ValueError, IndexError) as err:
        raise RecipeError(f"{where}: bad template {template!r}: {err}") from None


def resolve_budget(spec: ExperimentSpec, budget: str | None) -> tuple[str | None, Budget]:
    name = budget if budget is not None else spec.default_budget
    if name is None:
        return None, Budget()
    if name not in spec.budgets:
        raise RecipeError(f"experiment {spec.name!r} has no budget {name!r}; budgets: {sorted(spec.budgets) or '(none)'}")
    return name, spec.budgets[name]


def default_output(spec: ExperimentSpec, budget: str | None) -> Path | str:
    if spec.output:
        return spec.output if is_url(spec.output) else Path(spec.output)
    return Path("runs") / "experiments" / (spec.name + (f"-{budget}" if budget else ""))


def unused_axes(spec: ExperimentSpec) -> list[str]:
    """Axes that change nothing: no value brings a recipe or overrides and no template names ``{axis}``; their
    values plan identical runs (the same training repeated under other names)."""
    import string

    templates = [spec.recipe or "", *spec.overrides, *(o for b in spec.budgets.values() for o in b.overrides)]
    templates += [t for vals in spec.axes.values() for v in vals for t in (v.recipe or "", *v.overrides)]
    named = set()
    for t in templates:
        try:
            named |= {f.split(".")[0].split("[")[0] for _, f, _, _ in string.Formatter().parse(t) if f}
        except ValueError:  # a malformed template is reported when it is filled
            continue
    return [a for a, vals in spec.axes.items()
            if a not in named and not any(v.recipe or v.overrides for v in vals)]


def plan_runs(spec: ExperimentSpec, output: str | os.PathLike, budget: str | None = None) -> list[PlannedRun]:
    """Every run of the spec under ``budget``: axes product x seeds, recipe and overrides filled in.

    An axis that changes nothing (:func:`unused_axes`) is planned anyway, with an
    :class:`~adarl.errors.AdaRLWarning`: its runs would repeat the same training."""
    import warnings

    for axis in unused_axes(spec):
        names = [v.name for v in spec.axes[axis]]
        warnings.warn(f"experiment {spec.name!r}: axis {axis!r} changes nothing (no override or recipe uses "
                      f"{{{axis}}} and its values {names} bring none), so its runs repeat the same training; use "
                      f"{{{axis}}} in an override, give its values overrides, or remove it", AdaRLWarning, stacklevel=2)
    _, b = resolve_budget(spec, budget)
    seeds = b.seeds if b.seeds is not None else spec.seeds
    axes = {a: [v for v in vals if a not in b.axes or v.name in b.axes[a]] for a, vals in spec.axes.items()}
    url = is_url(output)
    out = str(output).rstrip("/") if url else Path(output)
    runs = []
    for combo in itertools.product(*axes.values()) if axes else [()]:
        named = dict(zip(axes, combo))
        for seed in seeds:
            values = {a: v.name for a, v in named.items()} | {"seed": str(seed)}
            recipe_t = spec.recipe
            overrides_t = list(spec.overrides)
            for v in named.values():
                if v.recipe:
                    recipe_t = v.recipe
                overrides_t += v.overrides
            overrides_t += b.overrides
            run_id = "__".join([f"{a}={v.name}" for a, v in named.items()] + [f"seed={seed}"])
            recipe = _fill(recipe_t, values, f"run {run_id} recipe")
            overrides = [_fill(o, values, f"run {run_id} override") for o in overrides_t] + [f"seed={seed}"]
            runs.append(PlannedRun(run_id, {a: v.name for a, v in named.items()}, seed, recipe, overrides,
                                   f"{out}/{run_id}" if url else str(out / run_id)))
    return runs


def run_is_finished(path: str | os.PathLike) -> bool:
    """A run folder (or URL) whose summary shows its whole frame budget spent."""
    if is_url(path):
        from adarl.results import join, read_text

        summary, recipe = read_text(join(path, "summary.json")), read_text(join(path, "recipe.yaml"))
        if summary is None or recipe is None:
            return False
        try:
            total = int(yaml.safe_load(recipe)["collector"]["total_frames"])
            return int(json.loads(summary).get("frames", -1)) >= total
        except (ValueError, KeyError, TypeError, AttributeError, yaml.YAMLError, json.JSONDecodeError):
            return False
    p = Path(path)
    summary, recipe = p / "summary.json", p / "recipe.yaml"
    if not (summary.is_file() and recipe.is_file()):
        return False
    try:
        frames = int(json.loads(summary.read_text()).get("frames", -1))
        total = int(yaml.safe_load(recipe.read_text())["collector"]["total_frames"])
    except (ValueError, KeyError, TypeError, yaml.YAMLError, json.JSONDecodeError):
        return False
    return frames >= total


def _check_recipes(runs: list[PlannedRun]) -> None:
    """Validate every run's recipe before anything runs: a missing recipe flags its runs, a bad one stops all."""
    from adarl.config import load_recipe

    problems = []
    for run in runs:
        try:
            load_recipe(run.recipe, run.overrides)
        except RecipeError as err:
            if str(err).startswith(f"no recipe named {run.recipe!r}") or "not found" in str(err).split("\n")[0]:
                run.status, run.message = "missing-recipe", str(err).split(";")[0]
            else:
                problems.append(f"{run.run_id}: {err}")
    if problems:
        raise RecipeError("experiment runs do not validate (nothing was run):\n" + "\n".join(problems[:10]))


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "adarl.cli", *args]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: the training process gets SIGKILL when its launcher process dies (a lost Ray worker, a killed job),
    so a retried run never races an orphan writing the same folder."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _record_attempt(run: PlannedRun, **event) -> None:
    if is_url(run.path):  # object stores cannot append: one small file per event, named so that they sort in order
        from adarl.results import join, write_atomic

        event = {"time": time.time(), "host": socket.gethostname(), "pid": os.getpid(), **event}
        name = f"{time.time_ns():020d}-{event['event']}-{uuid.uuid4().hex[:6]}.json"
        write_atomic(join(run.path.rsplit("/", 1)[0], ATTEMPTS_DIR, run.run_id, name), json.dumps(event) + "\n")
        return
    folder = Path(run.path).parent / ATTEMPTS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    event = {"time": time.time(), "host": socket.gethostname(), "pid": os.getpid(), **event}
    with (folder / f"{run.run_id}.jsonl").open("a") as fh:
        fh.write(json.dumps(event) + "\n")


def read_attempts(output: str | os.PathLike, run_id: str) -> list[dict]:
    """The start/end events of a run, in order (``event``: start | end; ``action``: ran | resumed | uploaded;
    ``pid``...). At a URL they are ``attempts/<run id>/*.json``, one file per event."""
    if is_url(output):
        from adarl.results import filesystem, join

        fs, folder = filesystem(join(output, ATTEMPTS_DIR, run_id))
        try:
            names = sorted(fs.ls(folder, detail=False))
        except FileNotFoundError:
            return []
        events = []
        for name in names:
            if name.endswith(".json"):
                try:
                    events.append(json.loads(fs.cat_file(name)))
                except (FileNotFoundError, ValueError):  # being written (local-like filesystems)
                    continue
        return sorted(events, key=lambda e: e.get("time", 0))
    f = Path(output) / ATTEMPTS_DIR / f"{run_id}.jsonl"
    if not f.is_file():
        return []
    return [json.loads(line) for line in f.read_text().splitlines() if line.strip()]


def execute_run(run: PlannedRun, threads: int | None) -> PlannedRun:
    """Run (or resume, when its folder has a checkpoint) one run with the ``adarl`` command; sets its status.

    What every launcher executes, wherever it runs; a finished run is left alone (``skipped-finished``). A run at a
    URL trains in a local scratch folder copied to the URL (:func:`_execute_at_url`)."""
    if is_url(run.path):
        return _execute_at_url(run, threads)
    path = Path(run.path)
    if run_is_finished(path):  # e.g. a retried task whose first try finished before its worker was lost
        run.status, run.message = "skipped-finished", "already finished"
        return run
    if (path / "checkpoints").is_dir() and any((path / "checkpoints").glob("ckpt-*.pt")):
        cmd, action = _cli("resume", str(path), "--quiet"), "resumed"
    else:
        if path.exists():
            shutil.rmtree(path)  # a start that never checkpointed: nothing to keep
        cmd, action = _cli("run", run.recipe, *run.overrides, "-o", str(path), "--quiet"), "ran"
    env = _train_env(threads)
    path.parent.mkdir(parents=True, exist_ok=True)
    log = path.parent / f"{run.run_id}.log"
    _record_attempt(run, event="start", action=action)
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env,
                              preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
    run.wall_time_s = time.perf_counter() - start
    if proc.returncode == 0 and run_is_finished(path):
        run.status, run.message = "finished", action
        log.unlink(missing_ok=True)
    else:
        tail = log.read_text().strip().splitlines()[-1:] if log.is_file() else []
        run.status, run.message = "failed", f"exit {proc.returncode}: {' '.join(tail)} (log: {log})"
    _record_attempt(run, event="end", action=action, status=run.status)
    return run


def _train_env(threads: int | None) -> dict:
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    return env


_POLL_S = 1.0  # how often a URL run's scratch folder is checked for a new checkpoint to upload


def _execute_at_url(run: PlannedRun, threads: int | None) -> PlannedRun:
    """:func:`execute_run` for a run at a URL: train in the local scratch folder (downloaded from the URL first when
    it lacks the URL's latest checkpoint), upload after each checkpoint and at the end (:class:`RunMirror`)."""
    from adarl.results import SYNC_INTERVAL_S, RunMirror, filesystem, join, scratch_folder, write_atomic

    if run_is_finished(run.path):
        run.status, run.message = "skipped-finished", "already finished"
        return run
    local = scratch_folder(run.path, run.run_id, run.scratch)
    local.parent.mkdir(parents=True, exist_ok=True)
    mirror = RunMirror(local, run.path)
    remote_log = join(run.path.rsplit("/", 1)[0], f"{run.run_id}.log")
    log = local.with_name(f"{run.run_id}.log")
    try:
        state = mirror.prepare()
    except Exception as err:  # noqa: BLE001 - e.g. the store does not answer: this attempt fails, others go on
        run.status, run.message = "failed", f"could not read {run.path}: {type(err).__name__}: {err}"
        return run
    if state == "fresh":
        cmd, action = _cli("run", run.recipe, *run.overrides, "-o", str(local), "--quiet"), "ran"
    elif run_is_finished(local):  # finished here, but the worker was lost before the upload ended
        cmd, action = None, "uploaded"
    else:
        cmd, action = _cli("resume", str(local), "--quiet"), "resumed"
    _record_attempt(run, event="start", action=action, scratch=str(local))
    start = time.perf_counter()
    returncode, upload_error = 0, None
    if cmd is not None:
        with log.open("w") as fh:
            proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=_train_env(threads),
                                    preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
            try:
                while True:
                    try:
                        returncode = proc.wait(timeout=_POLL_S)
                        break
                    except subprocess.TimeoutExpired:
                        pass
                    if mirror.has_new_checkpoint() or time.monotonic() - mirror.last_push >= SYNC_INTERVAL_S:
                        try:
                            mirror.push()
                        except Exception as err:  # noqa: BLE001 - retried at the next checkpoint; the run goes on
                            fh.write(f"adarl: upload to {run.path} failed (retrying later): {err}\n")
                            fh.flush()
            except BaseException:
                proc.kill()
                proc.wait()
                raise
    run.wall_time_s = time.perf_counter() - start
    finished_here = returncode == 0 and run_is_finished(local)
    try:
        mirror.push(final=finished_here)
        upload_error = None
    except Exception as err:  # noqa: BLE001 - reported below; the scratch folder is kept for a retry
        upload_error = err
    if finished_here and upload_error is None and run_is_finished(run.path):
        run.status, run.message = "finished", action
        mirror.clean()
        log.unlink(missing_ok=True)
        fs, rpath = filesystem(remote_log)
        if fs.exists(rpath):  # the log of an earlier failed attempt
            fs.rm(rpath)
    elif finished_here:
        why = upload_error or "its summary.json is not readable there"
        run.status, run.message = "failed", f"finished in {local} but the upload to {run.path} failed: {why}"
    else:
        tail = log.read_text().strip().splitlines()[-1:] if log.is_file() else []
        try:
            write_atomic(remote_log, log.read_text() if log.is_file() else "")
            where = remote_log
        except Exception:  # noqa: BLE001 - the local log is still there
            where = str(log)
        run.status, run.message = "failed", f"exit {returncode}: {' '.join(tail)} (log: {where})"
    _record_attempt(run, event="end", action=action, status=run.status)
    return run


_execute = execute_run


def _sweep(run: PlannedRun, sweeps: list[SweepSpec]) -> None:
    """Run the spec's sweeps missing from a finished run; a URL run is swept in a local copy, then uploaded."""
    from adarl.sweep import parse_sweep, sweep_run

    names: dict[str, SweepSpec] = {}
    for s in sweeps:
        names.setdefault(s.name or "__".join(p.split("=")[0] for p in s.params), s)
    if not is_url(run.path):
        for name, s in names.items():
            if not (Path(run.path) / "sweeps" / f"{name}.csv").is_file():
                sweep_run(run.path, [parse_sweep(p) for p in s.params], episodes=s.episodes, name=name)
        return
    import tempfile

    from adarl.results import RunMirror, exists, join, upload_tree

    todo = {n: s for n, s in names.items() if not exists(join(run.path, "sweeps", f"{n}.csv"))}
    if not todo:
        return
    with tempfile.TemporaryDirectory(prefix="adarl-sweep-") as tmp:
        mirror = RunMirror(Path(tmp) / run.run_id, run.path)
        latest = mirror.remote_latest()
        if latest is None:
            raise AdaRLError(f"cannot sweep {run.path}: it has no checkpoint (checkpoints/LATEST is missing)")
        mirror.download(latest)
        for name, s in todo.items():
            sweep_run(mirror.local, [parse_sweep(p) for p in s.params], episodes=s.episodes, name=name)
        upload_tree(mirror.local / "sweeps", join(run.path, "sweeps"))


def _write_state(out: Path | str, spec: ExperimentSpec, budget: str | None, runs: list[PlannedRun],
                 command: str = "") -> None:
    payload = {"name": spec.name, "description": spec.description, "budget": budget, "command": command,
               "axes": list(spec.axes),
               "report": spec.report.model_dump(), "runs": [r.as_dict() for r in runs]}
    if is_url(out):
        from adarl.results import join, write_atomic

        write_atomic(join(out, EXPERIMENT_FILE), json.dumps(payload, indent=2) + "\n")
        return
    tmp = out / (EXPERIMENT_FILE + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    os.replace(tmp, out / EXPERIMENT_FILE)


def _read_previous(out: Path | str) -> str | None:
    if is_url(out):
        from adarl.results import join, read_text

        return read_text(join(out, EXPERIMENT_FILE))
    previous = out / EXPERIMENT_FILE
    return previous.read_text() if previous.is_file() else None


def run_experiment(spec_path: str | os.PathLike, *, budget: str | None = None, output: str | os.PathLike | None = None,
                   workers: int | None = None, dry_run: bool = False, report: bool = True,
                   log=print, launcher: str | Any = "local", launcher_options: dict | None = None,
                   progress_interval: float = 0, scratch: str | os.PathLike | None = None,
                   live: bool = False, console=None) -> list[PlannedRun]:
    """Run (or continue) the experiment in ``spec_path``; returns the runs with their status.

    ``output``: a folder, or an fsspec URL (``s3://bucket/exp``, ``file:///shared/exp``; see :mod:`adarl.results`),
    where each run then trains in ``scratch`` (default: ``$TMPDIR/adarl-scratch`` of the machine it runs on) and is
    uploaded after each checkpoint. ``launcher``: ``local`` (default), ``ray``, ``submitit`` (see
    :mod:`adarl.launchers`; ``launcher_options`` go to :func:`~adarl.launchers.make_launcher`) or a
    :class:`~adarl.launchers.Launcher`. ``progress_interval`` > 0 logs one line per run and an aggregate bar that
    often (seconds); with ``live`` a table redrawn in place instead (rich, on ``console``: default stdout)."""
    spec = load_experiment(spec_path)
    budget, _ = resolve_budget(spec, budget)
    out = output if output is not None else default_output(spec, budget)
    out = str(out).rstrip("/") if is_url(out) else Path(out)
    if is_url(out):
        from adarl.results import filesystem

        filesystem(out)  # an unknown protocol or a missing backend package fails here, before anything runs
    runs = plan_runs(spec, out, budget)
    if scratch is not None:
        if is_url(out):
            for r in runs:
                r.scratch = str(scratch)
        else:
            log(f"note: --scratch is ignored: results at a local path ({out}) are written in place")
    _check_recipes(runs)
    todo = []
    for r in runs:
        if r.status == "missing-recipe":
            log(f"[skip] {r.run_id}: {r.message}")
        elif run_is_finished(r.path):
            r.status, r.message = "skipped-finished", "already finished"
        else:
            todo.append(r)
    previous = _read_previous(out)
    if previous is not None:  # keep the timings of runs finished in earlier sessions
        try:
            before = {r["run_id"]: r for r in json.loads(previous).get("runs", [])}
        except (json.JSONDecodeError, AttributeError, TypeError):
            before = {}
        for r in runs:
            if r.status == "skipped-finished" and r.run_id in before:
                r.wall_time_s = float(before[r.run_id].get("wall_time_s") or 0.0)
    n_done = sum(r.status == "skipped-finished" for r in runs)
    log(f"experiment {spec.name} (budget {budget or 'default'}): {len(runs)} runs, {n_done} already finished, "
        f"{len(todo)} to run, {sum(r.status == 'missing-recipe' for r in runs)} with a missing recipe -> {out}")
    if dry_run:
        for r in runs:
            log(f"  {r.status:<16} {r.run_id}: {r.recipe} {' '.join(r.overrides)}")
        return runs
    if is_url(out):
        from adarl.results import makedirs

        makedirs(out)
    else:
        out.mkdir(parents=True, exist_ok=True)
    command = f"adarl experiment {spec_path}" + (f" --budget {budget}" if budget else "") + f" -o {out}"
    _write_state(out, spec, budget, runs, command)
    from adarl.launchers import Launcher, make_launcher
    from adarl.progress import LiveBoard, ProgressBoard

    if not isinstance(launcher, Launcher):
        launcher = make_launcher(launcher, workers=workers or spec.workers, output=out, resources=spec.resources,
                                 **(launcher_options or {}))
    if is_url(out) and out.startswith("memory://") and launcher.name != "local":
        raise AdaRLValueError(f"output {out!r}: memory:// lives in one process, which the {launcher.name} launcher's "
                              "workers cannot see; use a shared URL (s3://, gs://, file:///shared/...)")
    board, last_tick = ProgressBoard(runs), [time.monotonic()]
    screen = LiveBoard(board, console=console) if live and progress_interval > 0 else None
    say = screen.log if screen is not None else log

    def done(r: PlannedRun) -> None:
        say(f"[{r.status}] {r.run_id} ({r.wall_time_s:.0f} s){'' if r.status == 'finished' else ': ' + r.message}")
        _write_state(out, spec, budget, runs, command)
        if screen is not None:
            screen.update()

    def tick(running: set) -> None:
        board.running = running
        if progress_interval > 0 and time.monotonic() - last_tick[0] >= progress_interval:
            last_tick[0] = time.monotonic()
            if screen is not None:
                screen.update()
            else:
                for line in board.render():
                    log(line)

    if todo:
        if screen is not None:
            with screen:
                launcher.launch(todo, done, tick=tick)
        else:
            launcher.launch(todo, done, tick=tick)
    _, b = resolve_budget(spec, budget)
    sweeps = spec.sweeps if b.sweeps is None else b.sweeps
    if sweeps:
        for r in runs:
            if r.status in ("finished", "skipped-finished"):
                _sweep(r, sweeps)
    _write_state(out, spec, budget, runs, command)
    failed = [r for r in runs if r.status == "failed"]
    if report:
        from adarl.aggregate import write_aggregate_report

        path = write_aggregate_report([out], f"{out}/report" if is_url(out) else out / "report")
        log(f"report: {path}")
    if failed:
        raise AdaRLError(f"{len(failed)} of {len(runs)} runs failed: " + "; ".join(f"{r.run_id}: {r.message}"
                                                                               for r in failed[:5]))
    return runs
