r"""The runs a report reads: run folders (or experiment folders) become :class:`RunRecord`\ s grouped by their axes.

Nothing is typed in: every number comes from the run folders' ``eval.csv``, ``ranks.json``, ``metrics/``, ``sweeps/``
and ``summary.json``. A run's score follows the report's rule (``report.score_last``: the mean of its last N nominal
evaluations); seeds are the replicates of a setting (:class:`Group`). Private module of
:mod:`adarl.experiments.report`.
"""

from __future__ import annotations

import json
import math
import os
import re
import statistics
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from adarl.errors import AdaRLError
from adarl.experiments.execute import run_is_finished
from adarl.experiments.sweep import read_sweep
from adarl.runtime import metrics
from adarl.runtime.config import local_plugins
from adarl.runtime.fingerprint import training_values
from adarl.runtime.report import layer_label, rank_axis
from adarl.runtime.run_folder.results import exists, is_url, join
from adarl.runtime.run_folder.run_dir import RunDir


def is_single_run(path: str | os.PathLike) -> bool:
    if is_url(path):
        return exists(join(path, "recipe.yaml"))
    return (Path(path) / "recipe.yaml").is_file()


@dataclass
class RunRecord:
    """What the report needs from one run folder."""

    path: Path
    axes: dict[str, str]
    seed: int
    env_id: str
    recipe: dict
    evals: list[tuple[int, float]]  # (frames, mean) of each nominal-dynamics evaluation
    events: list[int]  # frames of rank events (truncations)
    rank_history: list[dict]
    updates: int
    sweeps: dict = field(default_factory=dict)  # name -> adarl.experiments.sweep.SweepResult
    eval_updates: list[int] = field(default_factory=list)  # optimisation steps at each evaluation
    # where the rank events lie in environment frames: (label, x of each event, x of the run's end), or the
    # optimisation steps when the run has nothing to convert them with (adarl.runtime.report.rank_axis)
    rank_x: tuple[str, list[int], int] | None = None

    def score(self, last: int = 1) -> float | None:
        """The mean of the last ``last`` nominal evaluations (all of them when it has fewer), None without one."""
        if not self.evals:
            return None
        return statistics.fmean(m for _, m in self.evals[-last:])

    @property
    def best(self) -> float | None:
        """Its best nominal evaluation (None without one)."""
        return max((m for _, m in self.evals), default=None)

    def score_at_updates(self, updates: int) -> float | None:
        """The first evaluation at or after ``updates`` optimisation steps (an iteration's end), else None."""
        for (_, mean), u in zip(self.evals, self.eval_updates):
            if u >= updates:
                return mean
        return None

    @property
    def final(self) -> float | None:
        return self.evals[-1][1] if self.evals else None


@dataclass
class Group:
    """Runs that differ only in their seed."""

    key: tuple[tuple[str, str], ...]
    runs: list[RunRecord]
    score_last: int = 1  # the report's rule: a run's score is the mean of its last `score_last` evaluations

    @property
    def label(self) -> str:
        return ", ".join(f"{a}={v}" for a, v in self.key) or "all"

    @property
    def scored(self) -> list[RunRecord]:
        """The runs with a score, one per seed (a seed found twice, e.g. in two experiment folders, counts once:
        the first found)."""
        out, seen = [], set()
        for r in self.runs:
            if r.final is not None and r.seed not in seen:
                seen.add(r.seed)
                out.append(r)
        return out

    @property
    def duplicate_seeds(self) -> list[int]:
        seeds = [r.seed for r in self.runs if r.final is not None]
        return sorted({s for s in seeds if seeds.count(s) > 1})

    @property
    def scores(self) -> list[float]:
        """One score per seed, by the report's rule (:meth:`RunRecord.score`)."""
        return [r.score(self.score_last) for r in self.scored]

    finals = scores  # the name of a report whose score was the last evaluation alone

    def plateau_count(self, threshold: float) -> int:
        """Seeds whose best nominal evaluation exceeds ``threshold`` (left Hopper's stand-still plateau)."""
        return sum(1 for r in self.scored if r.best is not None and r.best > threshold)

    @property
    def mean(self) -> float:
        f = self.scores
        return statistics.fmean(f) if f else math.nan

    @property
    def std(self) -> float:
        f = self.scores
        return statistics.stdev(f) if len(f) > 1 else 0.0

    @property
    def seeds(self) -> list[int]:
        return sorted(r.seed for r in self.scored)


@dataclass
class Aggregate:
    groups: list[Group]
    axes: list[str]
    report: dict
    sources: list[str]
    info: dict

    def plateau_of(self, g: Group) -> float | None:
        """The report's plateau threshold for ``g``: one for every setting, or the one of ``g``'s value of the axis
        the report names per value (``{hopper: 1500, humanoid: 5500}``); None without one."""
        plateau = self.report.get("plateau")
        if not isinstance(plateau, dict):
            return None if plateau is None else float(plateau)
        for _, value in g.key:
            if str(value) in plateau:
                return float(plateau[str(value)])
        return None

    def group(self, **axes: str) -> Group:
        for g in self.groups:
            if dict(g.key) == {k: str(v) for k, v in axes.items()}:
                return g
        raise KeyError(axes)


def _load_run(path: Path, axes: dict[str, str] | None) -> RunRecord | None:
    if not is_single_run(path):
        return None
    run = RunDir(path)
    local_plugins.check_recorded(run.plugin_modules(), str(path))  # a changed one: refused
    recipe = yaml.safe_load((path / "recipe.yaml").read_text()) or {}
    rows = run.read_eval()
    evals = [(int(r["frames"]), float(r["mean"])) for r in rows]
    eval_updates = [int(r["updates"]) for r in rows]
    events = sorted({step for step, _ in metrics.series(run.scalars(), metrics.WARM_START_FRAMES)})
    summary_path = path / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    sweeps = {}
    sweep_dir = path / "sweeps"
    if sweep_dir.is_dir():
        for f in sorted(sweep_dir.glob("*.csv")):
            sweeps[f.stem] = read_sweep(f)
    if axes is None:
        axes = axes_from_run_id(path.name, recipe.get("seed")) or {"recipe": str(recipe.get("name", path.name))}
    return RunRecord(
        path,
        axes,
        int(recipe.get("seed", 0)),
        str(recipe.get("env", {}).get("id", "?")),
        recipe,
        evals,
        events,
        run.read_rank_history(),
        int(summary.get("updates", 0)),
        sweeps,
        eval_updates,
        rank_axis(run, run.read_rank_history()),
    )


def axes_from_run_id(name: str, seed) -> dict[str, str] | None:
    """The axes an experiment's run id names (``env=hopper__algorithm=adarl__seed=3``, or a rerun's folder
    ``...__seed=3.rerun1``), for a run folder copied out of its experiment (so ``adarl report`` on the copies groups
    them as the experiment did); None for any other name, or when the id's seed is not the recipe's."""
    name = re.sub(r"\.rerun\d+$", "", name)
    parts = [part.partition("=") for part in name.split("__")]
    if len(parts) < 2 or any(not sep or not key for key, sep, _ in parts) or parts[-1][0] != "seed":
        return None
    if parts[-1][2] != str(seed):
        return None
    return {key: value for key, _, value in parts[:-1]}


def collect_runs(dirs: list[str | os.PathLike]) -> tuple[list[RunRecord], dict]:
    """Run records from run folders, experiment folders (``experiment.json``) or folders holding run folders.

    An experiment folder that several budgets (or specs) ran into lists each one's runs in its ``experiment.json``
    (the last one's, and those it keeps under ``earlier``): every one of them is read, and when two of them have runs
    of the same setting (the same axes, other seeds or frames) the runs get a ``budget`` axis, so that a report never
    pools two budgets' runs as replicates of one setting."""
    runs: list[RunRecord] = []
    info: dict = {"experiments": [], "missing": [], "unfinished": []}
    seen: set[Path] = set()
    made_by: dict[int, str] = {}  # id(run record) -> the budget (experiment record) that lists it

    def add(rec: RunRecord | None, label: str | None = None) -> None:
        if rec is not None and rec.path.resolve() not in seen:
            seen.add(rec.path.resolve())
            runs.append(rec)
            if label is not None:
                made_by[id(rec)] = label

    for d in dirs:
        p = Path(d)
        if not p.is_dir():
            raise AdaRLError(
                f"{str(p)!r} is not a folder (expected a run folder, an experiment folder, or a folder of runs)"
            )
        exp = p / "experiment.json"
        if exp.is_file():
            state = json.loads(exp.read_text())
            records = [*[e for e in state.get("earlier") or [] if isinstance(e, dict)], state]
            info["experiments"] += [
                {k: e.get(k) for k in ("name", "description", "budget", "command", "axes", "report")} for e in records
            ]
            listed: set[str] = set()  # a run id is one run of the folder: the newest record's entry of it counts
            for e in reversed(records):
                label = f"{e.get('name')}:{e.get('budget') or 'default'}"
                for r in e.get("runs", []):
                    if r.get("run_id") not in listed:
                        listed.add(r.get("run_id"))
                        _add_listed(p, r, info, lambda rec, label=label: add(rec, label))
        elif is_single_run(p):
            add(_load_run(p, None))
        else:
            for sub in sorted(p.rglob("recipe.yaml")):
                if len(sub.relative_to(p).parts) <= 3:
                    add(_load_run(sub.parent, None))
    if not runs:
        raise AdaRLError(f"no run folders (with recipe.yaml) found in {[str(d) for d in dirs]}")
    _split_budgets(runs, made_by)
    _split_loose_variants(runs)
    return runs, info


def _add_listed(folder: Path, r: dict, info: dict, add) -> None:
    """One run an ``experiment.json`` lists: loaded when finished, else named as missing or unfinished."""
    if is_url(r["path"]):  # an experiment at a URL, read from a local copy (write_aggregate_report)
        r = {**r, "path": str(folder / r["path"].rstrip("/").rsplit("/", 1)[-1])}
    rp = Path(r["path"])
    if not rp.is_absolute() and not rp.exists():
        rp = folder / rp.name
    if r.get("status") == "missing-recipe":
        info["missing"].append(f"{r['run_id']} ({r['recipe']})")
        return
    rp = rp if rp.exists() else folder / Path(r["path"]).name
    if not run_is_finished(rp):
        info["unfinished"].append(r["run_id"])
        return
    add(_load_run(rp, dict(r["axes"])))


def _split_budgets(runs: list[RunRecord], made_by: dict[int, str]) -> None:
    """Give the runs of experiment folders a ``budget`` axis when one setting holds runs of two budgets."""
    budgets: dict[tuple, set[str]] = {}
    for r in runs:
        if id(r) in made_by:
            budgets.setdefault(tuple(sorted(r.axes.items())), set()).add(made_by[id(r)])
    if any(len(b) > 1 for b in budgets.values()):
        for r in runs:
            if id(r) in made_by:
                r.axes["budget"] = made_by[id(r)]


def _split_loose_variants(runs: list[RunRecord]) -> None:
    """Loose run folders are grouped by recipe name; runs of one name with different settings (other than the
    seed) would then pool as replicates of one setting. Give those a ``variant`` axis naming the keys that differ.
    What a setting is, is the fingerprint's (:func:`adarl.runtime.fingerprint.training_values`): keys that only
    name, place, log, checkpoint or evaluate a run more or less often (``logging.*``, ``output.*``,
    ``checkpoint.interval``, ``eval.episodes``, ...) never split seeds into variants."""
    by_name: dict[str, list[RunRecord]] = {}
    for r in runs:
        if set(r.axes) == {"recipe"}:
            by_name.setdefault(r.axes["recipe"], []).append(r)
    for group in by_name.values():
        flats = [{k: v for k, v in training_values(r.recipe).items() if k != "seed"} for r in group]
        keys = sorted({k for f in flats for k in f if len({repr(g.get(k)) for g in flats}) > 1})
        if not keys:
            continue
        for r, f in zip(group, flats):
            r.axes["variant"] = ",".join(f"{k}={f.get(k)}" for k in keys)


def aggregate_runs(dirs: list[str | os.PathLike], report: dict | None = None) -> Aggregate:
    """Group the runs found in ``dirs`` by their axes (seeds are replicates). The layout and scoring rule are the
    experiments' ``report`` sections, then ``report`` (keys of :class:`~adarl.experiments.spec.ReportSpec`) over
    them: loose run folders have no spec to take the rule from."""
    runs, info = collect_runs(dirs)
    axes: list[str] = []
    for r in runs:
        axes += [a for a in r.axes if a not in axes]
    groups: dict[tuple, Group] = {}
    for r in runs:
        key = tuple((a, r.axes.get(a, "-")) for a in axes)
        groups.setdefault(key, Group(key, [])).runs.append(r)
    layout: dict = {}
    for e in info["experiments"]:
        layout.update({k: v for k, v in (e.get("report") or {}).items() if v is not None})
    layout.update(report or {})
    last = int(layout.get("score_last") or 1)
    for g in groups.values():
        g.runs.sort(key=lambda r: r.seed)
        g.score_last = last
    return Aggregate(list(groups.values()), axes, layout, [str(d) for d in dirs], info)


def _num_key(v: str):
    try:
        return (0, float(v), v)
    except ValueError:
        return (1, 0.0, v)


def rank_on_frames(run: RunRecord) -> bool:
    """Whether a run's rank events can be placed in environment frames (recorded, or converted from its log)."""
    return run.rank_x is not None and run.rank_x[0].startswith("environment frames")


def _rank_series(run: RunRecord, frames: bool = False) -> dict[str, list[tuple[int, int]]]:
    """Per layer, ``(x, rank)`` from the start through every event to the run's end; x is the optimisation step,
    or with ``frames`` the environment frames (as the learning curves; :func:`rank_on_frames` must hold)."""
    if frames and not rank_on_frames(run):
        raise ValueError(f"{run.path}: its rank events cannot be placed in environment frames")
    xs = run.rank_x[1] if frames else [int(ev.get("step", 0)) for ev in run.rank_history]
    end = run.rank_x[2] if frames else run.updates
    series: dict[str, list[tuple[int, int]]] = {}
    for ev, x in zip(run.rank_history, xs):
        for layer in ev.get("layers", []):
            name = layer_label(layer)
            pts = series.setdefault(name, [(0, int(layer["old_rank"]))])
            pts.append((x, int(layer["new_rank"])))
    for pts in series.values():
        if end > pts[-1][0]:
            pts.append((end, pts[-1][1]))
    return series


def rank_settling(run: RunRecord) -> dict[str, dict]:
    """Per layer: the final rank, the smallest rank it had, the step of its last change (None: never changed),
    how many rank events followed that change without changing it (the evidence that it settled), and the rule's
    own candidate at the last event (``last_candidate``: Eq. 10's proposal before the acceptance step; None when not
    recorded) beside the rank kept there."""
    out: dict[str, dict] = {}
    steps = [int(ev.get("step", 0)) for ev in run.rank_history]
    for ev in run.rank_history:
        step = int(ev.get("step", 0))
        for layer in ev.get("layers", []):
            name = layer_label(layer)
            d = out.setdefault(
                name,
                {
                    "initial": int(layer["old_rank"]),
                    "final": int(layer["old_rank"]),
                    "min": int(layer["old_rank"]),
                    "last_change": None,
                },
            )
            new = int(layer["new_rank"])
            if new != d["final"]:
                d["last_change"] = step
            d["final"] = new
            d["min"] = min(d["min"], new)
            d["last_candidate"] = layer.get("candidate")
    for d in out.values():
        d["events_after"] = sum(1 for s in steps if d["last_change"] is None or s > d["last_change"])
    return out


def event_dips(run: RunRecord, window: int) -> list[tuple[int, float, float]]:
    """``(event frame, mean training return in the window before, mean in the window after)`` per rank event
    that changed a rank, from the run's ``rollout/ep_rew_mean`` log (``train/episode_return`` or
    ``train.episode_return`` in run folders of older adarl versions; events without episodes on both sides are left
    out)."""
    returns = metrics.series(RunDir(run.path).scalars(), metrics.TRAIN_RETURN)
    out = []
    for e in run.events:
        before = [v for f, v in returns if e - window < f <= e]
        after = [v for f, v in returns if e < f <= e + window]
        if before and after:
            out.append((e, statistics.fmean(before), statistics.fmean(after)))
    return out
