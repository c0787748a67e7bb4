"""A run's report: a markdown summary and PNG plots, made only from the files in its run folder.

``plots/return.png``: training episode return and nominal-dynamics evaluation against frames, rank events as red
dashed lines (paper Fig. 3). ``plots/ranks.png``: each low-rank layer's rank over environment frames, as return.png
(Fig. 4).
``plots/speed.png``: optimisation steps per second against environment frames, rank events marked (the cost of an
update falls as the factorised layers lose rank). matplotlib (Agg backend, no display) draws them.
"""

from __future__ import annotations

import bisect
import json
import os
import statistics
import tempfile
from pathlib import Path

import yaml

from adarl.runtime import metrics
from adarl.runtime.config import local_plugins
from adarl.runtime.run_folder.results import download_results, is_url, join, upload_tree, write_atomic
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = [
    "write_report",
    "plot_returns",
    "plot_ranks",
    "plot_speed",
    "speed_by_phase",
    "pyplot",
    "named_ranks",
    "layer_label",
]


def pyplot():
    """matplotlib's pyplot on the Agg backend (PNGs without a display). Imported here, on first use: the backend
    must be chosen before pyplot is imported, and only reports draw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _title(run: RunDir, what: str) -> str:
    """``"<what>: <recipe name>, <env>, seed <s>"`` from the run's recipe (a plot read alone says whose it is)."""
    try:
        recipe = yaml.safe_load((run.path / "recipe.yaml").read_text()) or {}
    except (OSError, ValueError):
        recipe = {}
    env = (recipe.get("env") or {}).get("id", "?")
    return f"{what}: {recipe.get('name', run.path.name)}, {env}, seed {recipe.get('seed', '?')}"


def rank_ticks(ax, ranks) -> None:
    """A log2 rank axis whose ticks are the ranks the layers actually had (2^k ticks hid 11 and 14)."""
    from matplotlib.ticker import FixedLocator, NullLocator, ScalarFormatter

    ticks = sorted({int(r) for r in ranks if r})
    ax.set_yscale("log", base=2)
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_minor_locator(NullLocator())
    ax.yaxis.set_major_formatter(ScalarFormatter())
    if len(ticks) > 14:  # too many to print: keep every other one and the ends
        ax.yaxis.set_major_locator(FixedLocator(sorted(set(ticks[::2]) | {ticks[0], ticks[-1]})))


def _event_frames(run: RunDir) -> list[int]:
    rows = metrics.series(run.scalars(), metrics.WARM_START_FRAMES)  # one row per event (older runs: rank.*)
    return sorted({step for step, _ in rows})


def plot_returns(run: RunDir, out: Path) -> Path | None:
    """Training return (per finished episode batch) and evaluation mean ± std, rank events marked."""
    train = metrics.series(run.scalars(), metrics.TRAIN_RETURN)
    evals = run.read_eval()
    if not train and not evals:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    if train:
        ax.plot([s for s, _ in train], [v for _, v in train], lw=0.8, alpha=0.6, label="training return (perturbed)")
    if evals:
        x = [int(r["frames"]) for r in evals]
        m = [float(r["mean"]) for r in evals]
        sd = [float(r["std"]) for r in evals]
        ax.errorbar(x, m, yerr=sd, fmt="o-", color="black", capsize=3, label="evaluation (nominal dynamics)")
    for i, f in enumerate(_event_frames(run)):
        ax.axvline(f, color="red", ls="--", lw=1, label="rank event" if i == 0 else None)
    ax.set_xlabel("environment frames")
    ax.set_ylabel("episode return")
    ax.set_title(_title(run, "return"), fontsize=9)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def _updates_to_frames(run: RunDir):
    """``updates -> frames`` from the run's ``train/n_updates`` log (frames at each logging point), linear between
    the points; None when the run logged none (a run folder of an older adarl without it)."""
    pts = sorted((int(v), int(f)) for f, v in metrics.series(run.scalars(), metrics.TRAIN_UPDATES))
    if len(pts) < 2:
        return None

    def convert(u: int) -> int:
        i = bisect.bisect_left([p[0] for p in pts], u)
        (u0, f0), (u1, f1) = pts[max(0, min(i - 1, len(pts) - 2))], pts[max(1, min(i, len(pts) - 1))]
        return int(round(f0 + (f1 - f0) * (u - u0) / (u1 - u0))) if u1 != u0 else f0

    return convert


def rank_axis(run: RunDir, history: list[dict]) -> tuple[str, list[int], int]:
    """Where a run's rank events lie on its plots' x axis: ``(label, x of each event, x of the run's end)``.

    Environment frames, like ``return.png``: from each event's ``frames`` (recorded since issue 31); for older rank
    histories, converted from its optimisation step through the run's ``train/n_updates`` log (labelled so, the
    conversion interpolates between logging points); else the optimisation steps themselves (labelled so)."""
    try:
        summary = json.loads((run.path / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {}
    steps = [int(ev.get("step", 0)) for ev in history]
    if history and all(ev.get("frames") is not None for ev in history):
        return "environment frames", [int(ev["frames"]) for ev in history], int(summary.get("frames") or 0)
    convert = _updates_to_frames(run)
    if convert is not None:
        label = "environment frames (events placed from their optimisation step)"
        return label, [convert(s) for s in steps], int(summary.get("frames") or 0)
    return "optimisation steps", steps, int(summary.get("updates") or 0)


def plot_ranks(run: RunDir, out: Path) -> Path | None:
    """Rank of each low-rank layer against environment frames, as ``return.png`` (a step plot through every
    event; older histories: :func:`rank_axis`)."""
    history = run.read_rank_history()
    if not history:
        return None
    label, xs, end = rank_axis(run, history)
    series: dict[str, list[tuple[int, int]]] = {}
    for event, x in zip(history, xs):
        for layer in event.get("layers", []):
            name = layer_label(layer)
            pts = series.setdefault(name, [(0, int(layer["old_rank"]))])
            pts.append((x, int(layer["new_rank"])))
    if not series:  # events that truncate nothing (rank.truncate: false): no rank to draw
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, pts in series.items():
        if end > pts[-1][0]:
            pts = [*pts, (end, pts[-1][1])]
        ax.step([p[0] for p in pts], [p[1] for p in pts], where="post", marker="o", ms=3, label=name)
    ax.set_xlabel(label)
    ax.set_ylabel("rank")
    rank_ticks(ax, [p[1] for pts in series.values() for p in pts])
    ax.set_title(_title(run, "ranks"), fontsize=9)
    ax.legend(loc="best", fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def _speed_series(run: RunDir) -> list[tuple[int, float]]:
    """``(optimisation steps, updates/s)`` at each logging point: ``time/updates_per_s`` joined with
    ``train/n_updates`` on the frame count both are logged at."""
    scalars = run.scalars()
    updates = dict(metrics.series(scalars, metrics.TRAIN_UPDATES))
    return [(int(updates[f]), v) for f, v in metrics.series(scalars, metrics.UPDATES_PER_S) if f in updates and v > 0]


def speed_by_phase(run: RunDir) -> list[dict]:
    """Median updates/s between consecutive rank events (before the first, between events, after the last): the
    figures the report's speed table shows."""
    series = _speed_series(run)
    steps = sorted({int(ev.get("step", 0)) for ev in run.read_rank_history()})
    edges = [0, *steps, float("inf")]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        vals = [v for s, v in series if lo < s <= hi]
        if vals:
            out.append(
                {"from_step": lo, "to_step": hi, "points": len(vals), "median_updates_per_s": statistics.median(vals)}
            )
    return out


def plot_speed(run: RunDir, out: Path) -> Path | None:
    """Optimisation steps per second against environment frames (``return.png``'s and ``ranks.png``'s axis), rank
    events as red dashed lines."""
    series = [(int(f), v) for f, v in metrics.series(run.scalars(), metrics.UPDATES_PER_S) if v > 0]
    if not series:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot([s for s, _ in series], [v for _, v in series], lw=1, marker=".", ms=3, label="updates/s")
    history = run.read_rank_history()
    label, xs, _ = rank_axis(run, history)
    if not label.startswith("environment frames"):  # nothing to place the events in frames with: left out
        xs = []
    for i, x in enumerate(sorted(set(xs))):
        ax.axvline(x, color="red", ls="--", lw=1, label="rank event" if i == 0 else None)
    ax.set_xlabel("environment frames")
    ax.set_ylabel("updates per second")
    ax.set_title(_title(run, "speed"), fontsize=9)
    ax.set_ylim(bottom=0)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def write_report(path: str | os.PathLike) -> Path | str:
    """Write ``report.md`` and ``plots/*.png`` for the run folder at ``path``; returns the report's path.

    ``path`` may be an fsspec URL (:mod:`adarl.runtime.run_folder.results`): the report is made in a local copy of
    the run's files
    and
    uploaded beside them; the URL of ``report.md`` is returned."""
    if is_url(path):
        with tempfile.TemporaryDirectory(prefix="adarl-report-") as tmp:
            local = download_results(str(path), Path(tmp) / "run")
            md = write_report(local)
            upload_tree(local / "plots", join(str(path), "plots"))
            write_atomic(join(str(path), "report.md"), md.read_bytes())
        return join(str(path), "report.md")
    run = RunDir(path)
    local_plugins.check_recorded(run.plugin_modules(), str(run.path))  # changed: refused
    plots = run.path / "plots"
    plots.mkdir(exist_ok=True)
    ret = plot_returns(run, plots / "return.png")
    rk = plot_ranks(run, plots / "ranks.png")
    sp = plot_speed(run, plots / "speed.png")
    summary_path = run.path / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    evals = run.read_eval()
    history = run.read_rank_history()

    lines = [f"# Run report: {summary.get('name', run.path.name)}", ""]
    if summary:
        lines += [
            f"- frames: {summary.get('frames')}, optimisation steps: {summary.get('updates')}, "
            f"episodes: {summary.get('episodes')}",
            f"- wall time: {summary.get('wall_time_s', 0):.0f} s ({summary.get('updates_per_s', 0):.1f} updates/s)",
            f"- rank events: {summary.get('rank_events')}; final ranks: {named_ranks(summary)}",
        ]
        per_frame = summary.get("simulator_steps_per_frame")
        if per_frame is not None:
            line = f"- simulator steps: {per_frame} per frame, {summary.get('simulator_steps')} in all"
            if int(per_frame) > 1:
                line += (
                    f" (RNAC-DS probes {int(per_frame) - 1} noisy candidate next states before each real step: "
                    f"at equal frames it used {per_frame}x the simulator steps of a one-step method)"
                )
            lines.append(line)
        lines.append("")
    if evals:
        last = evals[-1]
        lines += [
            "## Evaluation on nominal dynamics",
            "",
            (
                f"Final: **{float(last['mean']):.1f} ± {float(last['std']):.1f}** "
                f"(std over {last['episodes']} episodes; 95% CI ± {float(last['ci95']):.1f}) "
                f"at {last['frames']} frames."
                if int(last["episodes"]) > 1
                else f"Final: **{float(last['mean']):.1f}** (one episode: no spread) at {last['frames']} frames."
            ),
            "",
            "| frames | updates | mean | std | episodes |",
            "|---:|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {r['frames']} | {r['updates']} | {float(r['mean']):.1f} | {float(r['std']):.1f} | {r['episodes']} |"
            for r in evals
        ]
        lines.append("")
    if history:
        lines += [
            "## Rank events",
            "",
            "The rule proposes a candidate; the acceptance step applies it only if the network's outputs on "
            "recent transitions change by at most the tolerance (relative output error), otherwise the layer "
            "keeps its rank. Energy and weight error are at the new rank (worst ensemble member).",
            "",
            "| step | network | layer | old rank | candidate | new rank | output error (candidate) | "
            "output error (new) | tolerance | retained energy | weight error | note |",
            "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for ev in history:
            for layer in ev.get("layers", []):
                err = layer.get("truncation_error")
                err = max(err) if isinstance(err, list) else err
                energy = layer.get("retained_energy")
                energy = min(energy) if isinstance(energy, list) else energy
                note = layer.get("note") or layer.get("skipped") or ""
                lines.append(
                    f"| {ev.get('step')} | {layer.get('network', '')} | {layer.get('name') or layer.get('layer', '')} "
                    f"| {layer.get('old_rank')} "
                    f"| {_int(layer.get('candidate'))} | {layer.get('new_rank')} "
                    f"| {_fmt(layer.get('candidate_error'))} "
                    f"| {_fmt(layer.get('error'))} | {_fmt(layer.get('tolerance'))} | {_fmt(energy)} | {_fmt(err)} "
                    f"| {note.replace('|', '/')} |"
                )
        lines.append("")
    lines += ["## Plots", ""]
    if ret:
        lines += [
            "Training and evaluation return; red dashed lines mark rank events.",
            "",
            "![return](plots/return.png)",
            "",
        ]
    if rk:
        lines += ["Rank per low-rank layer.", "", "![ranks](plots/ranks.png)", ""]
    if sp:
        phases = speed_by_phase(run)
        lines += [
            "Optimisation steps per second (training loop wall time, collection and evaluation included); red "
            "dashed lines mark rank events. Timings depend on what else ran on the machine.",
            "",
            "![speed](plots/speed.png)",
            "",
        ]
        if history and phases:
            lines += ["| optimisation steps | logging points | median updates/s |", "|---|---:|---:|"]
            lines += [
                f"| {p['from_step']} - {'end' if p['to_step'] == float('inf') else p['to_step']} | {p['points']} "
                f"| {p['median_updates_per_s']:.1f} |"
                for p in phases
            ]
            lines.append("")
    out = run.path / "report.md"
    out.write_text("\n".join(lines) + "\n")
    return out


def named_ranks(summary: dict) -> dict:
    """``summary.json``'s final ranks by human name (by module path for a run of an older adarl)."""
    names = summary.get("layer_names") or {}
    return {names.get(path, path): rank for path, rank in (summary.get("ranks") or {}).items()}


def layer_label(layer: dict) -> str:
    """What a person reads for a layer of ``ranks.json``: its human name (``actor.layer0``), or for a run folder
    written before layers had names, ``<network>:<module path>``."""
    return layer.get("name") or f"{layer.get('network', '')}:{layer.get('layer', '?')}"


def _int(x) -> str:
    return "-" if x is None else str(int(x))


def _fmt(x) -> str:
    try:
        return f"{float(x):.4g}"
    except (TypeError, ValueError):
        return "-"
