"""Aggregate many run folders (seeds x settings) into one report: tables, curves, ranks, sweeps, return vs rank.

``adarl report DIR...`` with several folders, or an experiment folder, lands here. Every number is read from the
run folders (``eval.csv``, ``ranks.json``, ``metrics/``, ``sweeps/``); nothing is typed in. Runs are grouped by
their experiment axes (from ``experiment.json``) or, for loose run folders, by recipe name; seeds are the
replicates. The final score of a run is its last nominal-dynamics evaluation mean; a group's score is the mean
± sample std of its seeds' scores (the paper's Table 1 convention), with the number of seeds shown.

Outputs in the report folder: ``report.md``, ``report.html``, ``table.csv``, ``runs.csv``, and per figure a PNG
with the CSV it was drawn from: ``learning_curves``, ``ranks``, ``return_vs_<axis>`` (Fig. 1), ``sweep_<name>``
(Fig. 8).
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
import statistics
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from adarl.errors import AdaRLError
from adarl.experiments.execute import run_is_finished
from adarl.experiments.stats import interval_estimate, poi_estimate
from adarl.experiments.sweep import read_sweep
from adarl.runtime import metrics
from adarl.runtime.report import layer_label, pyplot
from adarl.runtime.results import download_results, exists, is_url, join, upload_tree
from adarl.runtime.run_dir import RunDir

__all__ = [
    "RunRecord",
    "Group",
    "Aggregate",
    "collect_runs",
    "aggregate_runs",
    "write_aggregate_report",
    "is_single_run",
    "intrinsic_rank",
    "ACTION_DIMS",
]

#: Action dimension of the paper's environments: the intrinsic rank of Tiwari et al. is 2 * d_a + 1.
ACTION_DIMS = {
    "Hopper-v5": 3,
    "Walker2d-v5": 6,
    "Ant-v5": 8,
    "Humanoid-v5": 17,
    "HalfCheetah-v5": 6,
    "InvertedPendulum-v5": 1,
    "CartPole-v1": 1,
    "LinearCartPole-v0": 1,
}


def intrinsic_rank(env_id: str) -> int | None:
    """``2 * d_a + 1`` (Tiwari et al. 2025; paper Fig. 4) for a known env, else None."""
    d = ACTION_DIMS.get(env_id)
    return None if d is None else 2 * d + 1


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
    def finals(self) -> list[float]:
        return [r.final for r in self.scored]

    @property
    def mean(self) -> float:
        f = self.finals
        return statistics.fmean(f) if f else math.nan

    @property
    def std(self) -> float:
        f = self.finals
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

    def group(self, **axes: str) -> Group:
        for g in self.groups:
            if dict(g.key) == {k: str(v) for k, v in axes.items()}:
                return g
        raise KeyError(axes)


def _load_run(path: Path, axes: dict[str, str] | None) -> RunRecord | None:
    if not is_single_run(path):
        return None
    run = RunDir(path)
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
        axes = {"recipe": str(recipe.get("name", path.name))}
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
    )


def collect_runs(dirs: list[str | os.PathLike]) -> tuple[list[RunRecord], dict]:
    """Run records from run folders, experiment folders (``experiment.json``) or folders holding run folders."""
    runs: list[RunRecord] = []
    info: dict = {"experiments": [], "missing": [], "unfinished": []}
    seen: set[Path] = set()

    def add(rec: RunRecord | None) -> None:
        if rec is not None and rec.path.resolve() not in seen:
            seen.add(rec.path.resolve())
            runs.append(rec)

    for d in dirs:
        p = Path(d)
        if not p.is_dir():
            raise AdaRLError(
                f"{str(p)!r} is not a folder (expected a run folder, an experiment folder, or a folder of runs)"
            )
        exp = p / "experiment.json"
        if exp.is_file():
            state = json.loads(exp.read_text())
            info["experiments"].append(
                {k: state.get(k) for k in ("name", "description", "budget", "command", "axes", "report")}
            )
            for r in state.get("runs", []):
                if is_url(r["path"]):  # an experiment at a URL, read from a local copy (write_aggregate_report)
                    r = {**r, "path": str(p / r["path"].rstrip("/").rsplit("/", 1)[-1])}
                rp = Path(r["path"])
                if not rp.is_absolute() and not rp.exists():
                    rp = p / rp.name
                if r.get("status") == "missing-recipe":
                    info["missing"].append(f"{r['run_id']} ({r['recipe']})")
                    continue
                rp = rp if rp.exists() else p / Path(r["path"]).name
                if not run_is_finished(rp):
                    info["unfinished"].append(r["run_id"])
                    continue
                add(_load_run(rp, dict(r["axes"])))
        elif is_single_run(p):
            add(_load_run(p, None))
        else:
            for sub in sorted(p.rglob("recipe.yaml")):
                if len(sub.relative_to(p).parts) <= 3:
                    add(_load_run(sub.parent, None))
    if not runs:
        raise AdaRLError(f"no run folders (with recipe.yaml) found in {[str(d) for d in dirs]}")
    _split_loose_variants(runs)
    return runs, info


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


# Keys that differ between the seeds of one setting (or do not change what is learned).
_NOT_A_SETTING = ("seed", "name", "description", "output.")


def _split_loose_variants(runs: list[RunRecord]) -> None:
    """Loose run folders are grouped by recipe name; runs of one name with different settings (other than the
    seed) would then pool as replicates of one setting. Give those a ``variant`` axis naming the keys that differ."""
    by_name: dict[str, list[RunRecord]] = {}
    for r in runs:
        if set(r.axes) == {"recipe"}:
            by_name.setdefault(r.axes["recipe"], []).append(r)
    for group in by_name.values():
        flats = [{k: v for k, v in _flat(r.recipe).items() if not k.startswith(_NOT_A_SETTING)} for r in group]
        keys = sorted({k for f in flats for k in f if len({repr(g.get(k)) for g in flats}) > 1})
        if not keys:
            continue
        for r, f in zip(group, flats):
            r.axes["variant"] = ",".join(f"{k}={f.get(k)}" for k in keys)


def aggregate_runs(dirs: list[str | os.PathLike]) -> Aggregate:
    """Group the runs found in ``dirs`` by their axes (seeds are replicates)."""
    runs, info = collect_runs(dirs)
    axes: list[str] = []
    for r in runs:
        axes += [a for a in r.axes if a not in axes]
    groups: dict[tuple, Group] = {}
    for r in runs:
        key = tuple((a, r.axes.get(a, "-")) for a in axes)
        groups.setdefault(key, Group(key, [])).runs.append(r)
    for g in groups.values():
        g.runs.sort(key=lambda r: r.seed)
    report = {}
    for e in info["experiments"]:
        report.update({k: v for k, v in (e.get("report") or {}).items() if v is not None})
    return Aggregate(list(groups.values()), axes, report, [str(d) for d in dirs], info)


# ---------------------------------------------------------------------------------------------- formatting


def _num_key(v: str):
    try:
        return (0, float(v), v)
    except ValueError:
        return (1, 0.0, v)


def _cell(g: Group | None) -> str:
    if g is None or not g.finals:
        return "–"
    return f"{g.mean:.1f} ± {g.std:.1f} (n={len(g.finals)})"


def _table(agg: Aggregate) -> tuple[list[str], list[list[str]], list[tuple[int, int]]]:
    """Header, rows and the (row, col) cells to bold (the best mean of each row)."""
    col_axis = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    if col_axis is not None and len(agg.axes) >= 2:
        row_axes = [a for a in agg.axes if a != col_axis]
        cols = sorted({dict(g.key)[col_axis] for g in agg.groups}, key=_num_key)
        rows_keys = sorted(
            {tuple(dict(g.key)[a] for a in row_axes) for g in agg.groups}, key=lambda t: [_num_key(x) for x in t]
        )
        by = {tuple(dict(g.key)[a] for a in row_axes) + (dict(g.key)[col_axis],): g for g in agg.groups}
        header = [" / ".join(row_axes)] + cols
        rows, bold = [], []
        for i, rk in enumerate(rows_keys):
            gs = [by.get(rk + (c,)) for c in cols]
            rows.append([", ".join(rk)] + [_cell(g) for g in gs])
            means = [g.mean if g is not None and g.finals else -math.inf for g in gs]
            if max(means) > -math.inf:
                bold.append((i, 1 + means.index(max(means))))
        return header, rows, bold
    groups = sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])
    header = [" / ".join(agg.axes) or "runs", "final return (mean ± std across seeds)", "seeds"]
    rows = [[", ".join(v for _, v in g.key) or "all", _cell(g), ",".join(map(str, g.seeds))] for g in groups]
    means = [g.mean if g.finals else -math.inf for g in groups]
    bold = [(means.index(max(means)), 1)] if means and max(means) > -math.inf else []
    return header, rows, bold


def _csv(rows: list[list], header: list[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------- figures


def _panels(agg: Aggregate) -> tuple[str | None, dict[str, list[Group]]]:
    """Panels (one per row-key when a column axis exists) and the groups drawn in each."""
    col_axis = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    if col_axis is None or len(agg.axes) < 2:
        return None, {"": sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])}
    panels: dict[str, list[Group]] = {}
    for g in agg.groups:
        d = dict(g.key)
        panels.setdefault(", ".join(d[a] for a in agg.axes if a != col_axis), []).append(g)
    return col_axis, panels


def _line_label(g: Group, col_axis: str | None) -> str:
    return dict(g.key)[col_axis] if col_axis else g.label


def _subplots(plt, n: int):
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    fig, axs = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.6 * nrows), squeeze=False)
    for ax in axs.flat[n:]:
        ax.set_visible(False)
    return fig, list(axs.flat[:n])


def plot_learning_curves(agg: Aggregate, out: Path) -> tuple[Path | None, str]:
    """Nominal-dynamics evaluation vs frames, mean across seeds with a ±std band; rank events dotted."""
    col_axis, panels = _panels(agg)
    rows = []
    if not any(r.evals for g in agg.groups for r in g.runs):
        return None, ""
    plt = pyplot()
    fig, axs = _subplots(plt, len(panels))
    cmap = plt.get_cmap("viridis" if len(agg.groups) > 8 else "tab10")
    for ax, (title, groups) in zip(axs, panels.items()):
        for i, g in enumerate(groups):
            color = cmap(i / max(1, len(groups) - 1)) if len(agg.groups) > 8 else cmap(i % 10)
            # Seeds evaluate at slightly different frames when warm-start frames count towards the budget: each
            # evaluation goes to the end of its eval.interval bin, so the seeds' curves line up.
            width = int((g.runs[0].recipe.get("eval") or {}).get("interval") or 1)
            binned = [[(-(-ff // width) * width, m) for ff, m in r.evals] for r in g.scored]
            frames = sorted({f for ev in binned for f, _ in ev})
            xs, ms, ss = [], [], []
            for f in frames:
                vals = [m for ev in binned for ff, m in ev if ff == f]
                xs.append(f)
                ms.append(statistics.fmean(vals))
                ss.append(statistics.stdev(vals) if len(vals) > 1 else 0.0)
                rows.append([g.label, f, ms[-1], ss[-1], len(vals)])
            ax.plot(xs, ms, "o-", ms=3, color=color, label=_line_label(g, col_axis))
            ax.fill_between(
                xs, [m - s for m, s in zip(ms, ss)], [m + s for m, s in zip(ms, ss)], color=color, alpha=0.15
            )
            for f in g.runs[0].events:
                ax.axvline(f, color=color, ls=":", lw=1)
        ax.set_title(title or "nominal-dynamics evaluation", fontsize=9)
        ax.set_xlabel("frames (evaluations binned by eval.interval)")
        ax.set_ylabel("return (mean ± std over seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2 if len(groups) > 6 else 1)
    fig.tight_layout()
    fig.savefig(out / "learning_curves.png", dpi=110)
    plt.close(fig)
    csv_text = _csv(rows, ["group", "frames", "mean", "std", "seeds"])
    (out / "learning_curves.csv").write_text(csv_text)
    return out / "learning_curves.png", csv_text


def _rank_series(run: RunRecord) -> dict[str, list[tuple[int, int]]]:
    series: dict[str, list[tuple[int, int]]] = {}
    for ev in run.rank_history:
        step = int(ev.get("step", 0))
        for layer in ev.get("layers", []):
            name = layer_label(layer)
            pts = series.setdefault(name, [(0, int(layer["old_rank"]))])
            pts.append((step, int(layer["new_rank"])))
    for pts in series.values():
        if run.updates > pts[-1][0]:
            pts.append((run.updates, pts[-1][1]))
    return series


def plot_rank_trajectories(agg: Aggregate, out: Path) -> Path | None:
    """Rank of each low-rank layer over optimisation steps, every seed, with the 2*d_a+1 line (Fig. 4)."""
    groups = [g for g in agg.groups if any(r.rank_history for r in g.runs)]
    if not groups:
        return None
    groups = groups[:12]
    plt = pyplot()
    fig, axs = _subplots(plt, len(groups))
    rows = []
    for ax, g in zip(axs, groups):
        colors: dict[str, object] = {}
        cmap = plt.get_cmap("tab10")
        for r in g.runs:
            for name, pts in _rank_series(r).items():
                c = colors.setdefault(name, cmap(len(colors) % 10))
                ax.step(
                    [p[0] for p in pts],
                    [p[1] for p in pts],
                    where="post",
                    color=c,
                    alpha=0.7,
                    lw=1,
                    label=name if r is g.runs[0] else None,
                )
                rows += [[g.label, r.seed, name, s, k] for s, k in pts]
        ref = agg.report.get("intrinsic_rank") or intrinsic_rank(g.runs[0].env_id)
        if ref:
            ax.axhline(ref, color="red", ls="--", lw=1, label=f"intrinsic rank {ref}")
        ax.set_yscale("log", base=2)
        ax.set_title(f"{g.label} ({len(g.runs)} seeds)", fontsize=9)
        ax.set_xlabel("optimisation steps")
        ax.set_ylabel("rank")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "ranks.png", dpi=110)
    plt.close(fig)
    (out / "ranks.csv").write_text(_csv(rows, ["group", "seed", "layer", "step", "rank"]))
    return out / "ranks.png"


def rank_settling(run: RunRecord) -> dict[str, dict]:
    """Per layer: the final rank, the smallest rank it had, the step of its last change (None: never changed),
    and how many rank events followed that change without changing it (the evidence that it settled)."""
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
    for d in out.values():
        d["events_after"] = sum(1 for s in steps if d["last_change"] is None or s > d["last_change"])
    return out


def _rank_settling_blocks(agg: Aggregate, out: Path) -> list[tuple]:
    groups = [
        g
        for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])
        if any(r.rank_history for r in g.scored)
    ]
    rows, crow = [], []
    for g in groups:
        per_layer: dict[str, list] = {}
        for r in g.scored:
            for name, d in rank_settling(r).items():
                per_layer.setdefault(name, []).append((r.seed, d))
                crow.append(
                    [
                        *[v for _, v in g.key],
                        r.seed,
                        name,
                        d["initial"],
                        d["final"],
                        d["min"],
                        d["last_change"],
                        d["events_after"],
                        len(r.rank_history),
                    ]
                )
        for name, ds in per_layer.items():
            ds.sort()
            rows.append(
                [
                    g.label,
                    name,
                    str(ds[0][1]["initial"]),
                    ", ".join(str(d["final"]) for _, d in ds),
                    ", ".join(str(d["min"]) for _, d in ds),
                    ", ".join("never" if d["last_change"] is None else f"{d['last_change']:,}" for _, d in ds),
                    ", ".join(str(d["events_after"]) for _, d in ds),
                ]
            )
    if not rows:
        return []
    (out / "rank_settling.csv").write_text(
        _csv(
            crow,
            [
                *agg.axes,
                "seed",
                "layer",
                "initial_rank",
                "final_rank",
                "min_rank",
                "last_change_step",
                "events_after_last_change",
                "events",
            ],
        )
    )
    return [
        ("h", 2, "Do the ranks settle?"),
        (
            "p",
            "Per layer, one value per seed (seeds in increasing order): the final rank, the smallest rank it "
            "reached, the optimisation step of its last change, and the number of rank events after that "
            "change that left it unchanged. Data in rank_settling.csv.",
        ),
        (
            "table",
            ["setting", "layer", "initial", "final rank", "lowest rank", "last change at step", "events since"],
            rows,
            [],
        ),
    ]


def plot_return_vs(agg: Aggregate, axis: str, out: Path) -> Path | None:
    """Final return (mean ± std across seeds, error bars) against a numeric axis such as the rank (Fig. 1)."""
    if axis not in agg.axes:
        return None
    try:
        [float(dict(g.key)[axis]) for g in agg.groups]
    except ValueError:
        return None
    others = [a for a in agg.axes if a != axis]
    lines: dict[str, list[Group]] = {}
    for g in agg.groups:
        d = dict(g.key)
        lines.setdefault(", ".join(f"{a}={d[a]}" for a in others), []).append(g)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    rows = []
    for label, gs in lines.items():
        gs = sorted((g for g in gs if g.finals), key=lambda g: float(dict(g.key)[axis]))
        x = [float(dict(g.key)[axis]) for g in gs]
        ax.errorbar(x, [g.mean for g in gs], yerr=[g.std for g in gs], fmt="o-", capsize=4, label=label or None)
        rows += [[label, dict(g.key)[axis], g.mean, g.std, len(g.finals), json.dumps(g.finals)] for g in gs]
    ref = agg.report.get("intrinsic_rank")
    if ref and axis == "rank":
        ax.axvline(ref, color="red", ls="--", lw=1, label=f"intrinsic rank {ref}")
    ax.set_xlabel(axis)
    ax.set_ylabel("final nominal return (mean ± std over seeds)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / f"return_vs_{axis}.png", dpi=110)
    plt.close(fig)
    (out / f"return_vs_{axis}.csv").write_text(_csv(rows, ["line", axis, "mean", "std", "seeds", "finals"]))
    return out / f"return_vs_{axis}.png"


def plot_sweeps(agg: Aggregate, out: Path) -> list[tuple[str, Path, list[list]]]:
    """Per 1-D sweep name: mean across seeds of each grid point's mean, ±std band, red stars at the worst case."""
    names = sorted({n for g in agg.groups for r in g.runs for n, s in r.sweeps.items() if len(s.params) == 1})
    made = []
    for name in names:
        plt = pyplot()
        fig, ax = plt.subplots(figsize=(6.5, 4))
        rows, summary = [], []
        for g in agg.groups:
            results = [r.sweeps[name] for r in g.runs if name in r.sweeps]
            if not results:
                continue
            param = results[0].params[0]
            xs = [p.values[param] for p in results[0].points]
            ms, ss, ws = [], [], []
            for i, _ in enumerate(xs):
                vals = [res.points[i].mean for res in results]
                ms.append(statistics.fmean(vals))
                ss.append(statistics.stdev(vals) if len(vals) > 1 else 0.0)
                ws.append(min(res.points[i].worst for res in results))
                rows.append([g.label, param, xs[i], ms[-1], ss[-1], ws[-1], len(vals)])
            line = ax.plot(xs, ms, "o-", ms=3, label=g.label)[0]
            ax.fill_between(
                xs, [m - s for m, s in zip(ms, ss)], [m + s for m, s in zip(ms, ss)], color=line.get_color(), alpha=0.15
            )
            ax.plot(xs, ws, "*", color="red", ms=9)
            summary.append([g.label, len(results), statistics.fmean(ms), min(ms), min(ws)])
            ax.set_xlabel(param)
        ax.plot([], [], "*", color="red", label="worst case")
        ax.set_ylabel("return")
        ax.set_title(f"sweep {name}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"sweep_{name}.png", dpi=110)
        plt.close(fig)
        (out / f"sweep_{name}.csv").write_text(_csv(rows, ["group", "param", "value", "mean", "std", "worst", "seeds"]))
        made.append((name, out / f"sweep_{name}.png", summary))
    return made


# ---------------------------------------------------------------------------------------------- report


def _md_table(header: list[str], rows: list[list[str]], bold: list[tuple[int, int]] = ()) -> list[str]:
    rows = [list(r) for r in rows]
    for i, j in bold:
        rows[i][j] = f"**{rows[i][j]}**"
    out = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    return out + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]


def _html(blocks: list[tuple]) -> str:
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>adarl report</title><style>"
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}td:first-child{text-align:left}"
        "img{max-width:100%}</style></head><body>"
    ]
    for b in blocks:
        kind = b[0]
        if kind == "h":
            parts.append(f"<h{b[1]}>{html.escape(b[2])}</h{b[1]}>")
        elif kind == "p":
            parts.append(f"<p>{html.escape(b[1])}</p>")
        elif kind == "code":
            parts.append(f"<pre><code>{html.escape(b[1])}</code></pre>")
        elif kind == "table":
            header, rows, bold = b[1], b[2], set(b[3])
            parts.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
            for i, r in enumerate(rows):
                cells = [
                    f"<b>{html.escape(str(c))}</b>" if (i, j) in bold else html.escape(str(c)) for j, c in enumerate(r)
                ]
                parts.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
            parts.append("</table>")
        elif kind == "img":
            parts.append(f"<p><img src='{html.escape(b[1])}' alt='{html.escape(b[2])}'></p>")
    return "\n".join(parts) + "\n</body></html>\n"


def _markdown(blocks: list[tuple]) -> str:
    lines: list[str] = []
    for b in blocks:
        kind = b[0]
        if kind == "h":
            lines += ["#" * b[1] + " " + b[2], ""]
        elif kind == "p":
            lines += [b[1], ""]
        elif kind == "code":
            lines += ["```bash", b[1], "```", ""]
        elif kind == "table":
            lines += _md_table(b[1], b[2], b[3]) + [""]
        elif kind == "img":
            lines += [f"![{b[2]}]({b[1]})", ""]
    return "\n".join(lines)


def write_aggregate_report(
    dirs: list[str | os.PathLike], output: str | os.PathLike | None = None, *, command: str | None = None
) -> Path | str:
    """Aggregate the runs in ``dirs`` and write the report folder; returns the path of its ``report.md``.

    ``dirs`` and ``output`` may be fsspec URLs (:mod:`adarl.runtime.results`): the runs' files (not their checkpoints)
    are copied to a temporary folder, the report is made there and uploaded (default output: ``<URL>/report`` for one
    experiment at a URL); ``runs.csv`` names the runs by their URL, and the URL of ``report.md`` is returned."""
    if any(is_url(d) for d in dirs) or is_url(output):
        return _write_report_via_copy(dirs, output, command=command)
    agg = aggregate_runs(dirs)
    if output is None:
        only = Path(dirs[0]) if len(dirs) == 1 else None
        output = only / "report" if only is not None and (only / "experiment.json").is_file() else Path("report")
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    n_runs = sum(len(g.runs) for g in agg.groups)
    exps = agg.info["experiments"]
    title = "Experiment report: " + ", ".join(e["name"] for e in exps) if exps else "Aggregate report"
    blocks: list[tuple] = [("h", 1, title)]
    for e in exps:
        if e.get("description"):
            blocks.append(("p", f"{e['description']} (budget: {e.get('budget') or 'default'})."))
    blocks.append(
        (
            "p",
            f"{n_runs} runs in {len(agg.groups)} settings; seeds are replicates. Every number is read "
            "from the run folders listed in runs.csv. Score of a run: its last evaluation on the nominal "
            "dynamics (mean over its evaluation episodes); table cells: mean ± sample std of that score "
            "across seeds, n = number of seeds; best mean of each row in bold.",
        )
    )
    commands = [command] if command else [e["command"] for e in exps if e.get("command")]
    if commands:
        blocks += [("p", "Produced by:"), ("code", "\n".join(commands))]
    if agg.info["unfinished"]:
        blocks.append(("p", "Not finished (left out): " + "; ".join(agg.info["unfinished"])))
    if agg.info["missing"]:
        blocks.append(("p", "Not run (recipe missing): " + "; ".join(agg.info["missing"])))
    header, rows, bold = _table(agg)
    blocks += [("h", 2, "Final return on nominal dynamics"), ("table", header, rows, bold)]
    table_rows = [
        [
            *[v for _, v in g.key],
            len(g.finals),
            g.mean,
            g.std,
            min(g.finals, default=math.nan),
            max(g.finals, default=math.nan),
            json.dumps(g.seeds),
            json.dumps(g.finals),
        ]
        for g in agg.groups
    ]
    (out / "table.csv").write_text(
        _csv(table_rows, [*agg.axes, "n_seeds", "mean", "std", "min", "max", "seeds", "finals"])
    )
    (out / "runs.csv").write_text(
        _csv(
            [
                [
                    str(r.path),
                    *[r.axes.get(a, "-") for a in agg.axes],
                    r.seed,
                    r.env_id,
                    r.final,
                    r.evals[-1][0] if r.evals else None,
                    r.updates,
                ]
                for g in agg.groups
                for r in g.runs
            ],
            ["path", *agg.axes, "seed", "env_id", "final_return", "frames", "updates"],
        )
    )

    blocks += _statistics_blocks(agg, out)

    x_axis = agg.report.get("x_axis") or ("rank" if "rank" in agg.axes else None)
    if x_axis:
        p = plot_return_vs(agg, x_axis, out)
        if p is not None:
            blocks += [
                ("h", 2, f"Final return vs {x_axis}"),
                ("p", "Mean ± std across seeds (error bars); data in " + p.with_suffix(".csv").name + "."),
                ("img", p.name, f"return vs {x_axis}"),
            ]
    p, _ = plot_learning_curves(agg, out)
    if p is not None:
        blocks += [
            ("h", 2, "Learning curves"),
            (
                "p",
                "Nominal-dynamics evaluation against environment frames: mean across seeds, shaded ± std; "
                "dotted lines mark rank events (truncations). Data in learning_curves.csv.",
            ),
            ("img", p.name, "learning curves"),
        ]
    p = plot_rank_trajectories(agg, out)
    if p is not None:
        blocks += [
            ("h", 2, "Rank trajectories"),
            (
                "p",
                "Rank of each factorised layer over optimisation steps, every seed; the red dashed line is "
                "the intrinsic rank (2*d_a+1, Tiwari et al. 2025; or the spec's report.intrinsic_rank). "
                "Data in ranks.csv.",
            ),
            ("img", p.name, "ranks"),
        ]
    blocks += _rank_settling_blocks(agg, out)
    for name, path, summary in plot_sweeps(agg, out):
        blocks += [
            ("h", 2, f"Robustness sweep: {name}"),
            (
                "p",
                "Per grid point: mean across seeds of the per-point mean return, shaded ± std across seeds; "
                "red stars: worst single episode over all seeds. Data in " + path.with_suffix(".csv").name,
            ),
            (
                "table",
                ["group", "seeds", "average over grid", "worst mean", "worst case"],
                [[s[0], s[1], f"{s[2]:.1f}", f"{s[3]:.1f}", f"{s[4]:.1f}"] for s in summary],
                [],
            ),
            ("img", path.name, f"sweep {name}"),
        ]
    (out / "report.md").write_text(_markdown(blocks))
    (out / "report.html").write_text(_html(blocks))
    return out / "report.md"


def _ci(point: float, lo: float, hi: float) -> str:
    if math.isnan(point):
        return "–"
    return f"{point:.1f} [{lo:.1f}, {hi:.1f}]" if not math.isnan(lo) else f"{point:.1f}"


def _statistics_blocks(agg: Aggregate, out: Path) -> list[tuple]:
    """IQM and mean with stratified bootstrap intervals, probability of improvement over the reference column,
    and scores at the optimisation steps the spec names (adarl.experiments.stats); writes statistics.csv."""
    col_axis = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    ref = agg.report.get("reference")
    groups = sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])

    def _seed_counts(gs) -> str:
        ns = sorted({len(g.finals) for g in gs if g.finals})
        if not ns:
            return "no finished seeds"
        n = f"{ns[0]}" if len(ns) == 1 else f"{ns[0]}-{ns[-1]}"
        return f"{n} seed{'s' if ns[-1] > 1 else ''} per setting"

    def partner(g: Group) -> Group | None:
        if ref is None or col_axis is None or dict(g.key).get(col_axis) == ref:
            return None
        want = {**dict(g.key), col_axis: ref}
        return next((h for h in agg.groups if dict(h.key) == want), None)

    header = ["setting", "n", "mean ± std", "mean [95% CI]", "IQM [95% CI]"]
    if ref is not None:
        header.append(f"P({ref} > setting) [95% CI]")
    rows, csv_rows = [], []
    for g in groups:
        f = g.finals
        m = interval_estimate(f, "mean")
        q = interval_estimate(f, "iqm")
        row = [g.label, str(len(f)), f"{g.mean:.1f} ± {g.std:.1f}" if f else "–", _ci(*m), _ci(*q)]
        p = (math.nan,) * 3
        h = partner(g)
        if ref is not None:
            if h is not None and h.finals and f:
                p = poi_estimate(h.finals, f)
                row.append(f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]")
            else:
                row.append("–")
        rows.append(row)
        csv_rows.append([*[v for _, v in g.key], len(f), g.mean, g.std, *m, *q, *p])
    names = [
        *agg.axes,
        "n_seeds",
        "mean",
        "std",
        "mean_pt",
        "mean_lo",
        "mean_hi",
        "iqm",
        "iqm_lo",
        "iqm_hi",
        "poi_ref",
        "poi_lo",
        "poi_hi",
    ]
    (out / "statistics.csv").write_text(_csv(csv_rows, names))
    blocks: list[tuple] = [
        ("h", 2, "Statistics across seeds"),
        (
            "p",
            "Each seed counted once. Mean and interquartile mean (IQM: the mean of the middle 50% of the seeds' "
            "scores) with 95% stratified-bootstrap percentile intervals (2000 resamples of the seeds within each "
            "env, fixed seed), computed by adarl.experiments.stats as the rliable library defines them"
            + (
                f"; P({ref} > setting): the probability that a run of {ref} scores above a run of the setting "
                "(ties count half), with its bootstrap interval"
                if ref is not None
                else ""
            )
            + f". With {_seed_counts(groups)} the intervals are wide. Data in statistics.csv.",
        ),
        ("table", header, rows, []),
    ]
    dups = [f"{g.label}: seeds {g.duplicate_seeds}" for g in groups if g.duplicate_seeds]
    if dups:
        blocks.append(("p", "Seeds found more than once (counted once, the first run found): " + "; ".join(dups)))
    window = agg.report.get("event_window")
    if window:
        blocks += _event_window_blocks(groups, int(window), out, col_axis=col_axis, ref=ref)
    at = list(agg.report.get("at_updates") or [])
    if at:
        head = ["setting"] + [f"at {u:,} steps" for u in at]
        trows, crow = [], []
        for g in groups:
            cells = []
            for u in at:
                vals = [v for v in (r.score_at_updates(u) for r in g.scored) if v is not None]
                q = interval_estimate(vals, "iqm")
                mean = statistics.fmean(vals) if vals else math.nan
                sd = statistics.stdev(vals) if len(vals) > 1 else 0.0
                cells.append(f"{mean:.1f} ± {sd:.1f}; IQM {_ci(*q)} (n={len(vals)})" if vals else "–")
                crow.append([*[v for _, v in g.key], u, len(vals), mean, sd, *q])
            trows.append([g.label, *cells])
        (out / "at_updates.csv").write_text(
            _csv(crow, [*agg.axes, "updates", "n_seeds", "mean", "std", "iqm", "iqm_lo", "iqm_hi"])
        )
        blocks += [
            ("h", 2, "Score at the end of each iteration"),
            (
                "p",
                "Each run's first nominal-dynamics evaluation at or after the given number of optimisation "
                "steps: mean ± std across seeds; IQM [95% CI]. Data in at_updates.csv.",
            ),
            ("table", head, trows, []),
        ]
    return blocks


def event_dips(run: RunRecord, window: int) -> list[tuple[int, float, float]]:
    """``(event frame, mean training return in the window before, mean in the window after)`` per rank event
    that changed a rank, from the run's ``train/episode_return`` log (``train.episode_return`` in run folders of
    an older adarl; events without episodes on both sides are left out)."""
    returns = metrics.series(RunDir(run.path).scalars(), metrics.TRAIN_RETURN)
    out = []
    for e in run.events:
        before = [v for f, v in returns if e - window < f <= e]
        after = [v for f, v in returns if e < f <= e + window]
        if before and after:
            out.append((e, statistics.fmean(before), statistics.fmean(after)))
    return out


def _event_window_blocks(
    groups: list[Group], window: int, out: Path, *, col_axis: str | None = None, ref: str | None = None
) -> list[tuple]:
    rows, crow, per_seed = [], [], {}
    for g in groups:
        changes, afters, seeds = [], [], {}
        for r in g.scored:
            for e, before, after in event_dips(r, window):
                changes.append(after - before)
                seeds.setdefault(r.seed, []).append(after - before)
                afters.append(after / before if before else math.nan)
                crow.append([*[v for _, v in g.key], r.seed, e, before, after])
        if not changes:
            continue
        # the seed is the unit: each seed's mean change over its events, then a bootstrap over seeds
        per_seed[g.key] = [statistics.fmean(v) for v in seeds.values()]
        rows.append(
            (
                g,
                [
                    g.label,
                    str(len(changes)),
                    str(len(seeds)),
                    f"{statistics.fmean(changes):+.1f}",
                    _ci(*interval_estimate(per_seed[g.key], "mean")),
                    f"{min(changes):+.1f}",
                    f"{statistics.fmean(a for a in afters if not math.isnan(a)):.2f}",
                ],
            )
        )
    if not rows:
        return []
    header = ["setting", "events", "seeds", "mean change", "mean of seed means [95% CI]", "worst change"]
    header.append("mean after / before")
    with_ref = ref is not None and col_axis is not None
    if with_ref:
        header.append(f"P({ref} dips less) [95% CI]")
    table = []
    for g, row in rows:
        if with_ref:
            key = dict(g.key)
            ref_key = tuple((a, ref if a == col_axis else v) for a, v in g.key)
            if key.get(col_axis) != ref and ref_key in per_seed:
                p = poi_estimate(per_seed[ref_key], per_seed[g.key])
                row.append(f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]")
            else:
                row.append("–")
        table.append(row)
    (out / "event_window.csv").write_text(
        _csv(crow, [*[a for a, _ in groups[0].key], "seed", "event_frames", "return_before", "return_after"])
    )
    return [
        ("h", 2, "Training return around rank events"),
        (
            "p",
            f"For every rank event that changed a rank, in every seed: the mean training episode return in "
            f"the {window:,} frames after the event minus the mean in the {window:,} frames before it (the "
            "transient dip of Fig. 9; training episodes run under the perturbed dynamics, so single values are "
            "noisy). Mean change: over all events; mean of seed means: each seed's mean over its events, counted "
            "once, with a 95% bootstrap interval over seeds"
            + (
                f"; P({ref} dips less): the probability that a seed of {ref} has a higher mean change than a seed "
                "of the setting (ties count half), with its bootstrap interval"
                if with_ref
                else ""
            )
            + ". Data in event_window.csv.",
        ),
        ("table", header, table, []),
    ]


def _write_report_via_copy(dirs: list, output, *, command: str | None) -> Path | str:
    if output is None:
        only = dirs[0] if len(dirs) == 1 else None
        if only is not None and is_url(only) and exists(join(only, "experiment.json")):
            output = join(only, "report")
        elif only is not None and not is_url(only) and (Path(only) / "experiment.json").is_file():
            output = Path(only) / "report"
        else:
            output = Path("report")
    with tempfile.TemporaryDirectory(prefix="adarl-report-") as tmp:
        local_dirs, names = [], {}
        for i, d in enumerate(dirs):
            if is_url(d):
                copy = download_results(str(d), Path(tmp) / f"in{i}")
                names[str(copy)] = str(d).rstrip("/")
                local_dirs.append(copy)
            else:
                local_dirs.append(d)
        local_out = Path(tmp) / "out" if is_url(output) else Path(output)
        md = write_aggregate_report(local_dirs, local_out, command=command)
        runs_csv = local_out / "runs.csv"
        rows = list(csv.reader(io.StringIO(runs_csv.read_text())))
        for row in rows[1:]:  # local copies -> the URLs they came from
            for copy, url in names.items():
                if row[0] == copy or row[0].startswith(copy + os.sep):
                    row[0] = url + row[0][len(copy) :].replace(os.sep, "/")
        buf = io.StringIO()
        csv.writer(buf).writerows(rows)
        runs_csv.write_text(buf.getvalue())
        if not is_url(output):
            return md
        upload_tree(local_out, str(output))
    return join(str(output), "report.md")
