"""A run's report: a markdown summary and plots (PNG, with PDF and SVG beside each), made only from the files in its
run folder.

``plots/return.png``: training episode return and nominal-dynamics evaluation against frames, rank events as red
dashed lines (paper Fig. 3). ``plots/ranks.png``: each low-rank layer's rank over environment frames, as return.png
(Fig. 4).
``plots/speed.png``: optimisation steps per second against environment frames, rank events marked (the cost of an
update falls as the factorised layers lose rank). matplotlib (Agg backend, no display) draws them, in the style every
report figure shares (:data:`PAPER_RC`: 7-8 pt text at a paper's column width, constrained layout, legends below the
axes; :func:`save_figure` writes each in :data:`FIGURE_FORMATS`).
"""

from __future__ import annotations

import bisect
import functools
import json
import os
import re
import statistics
import tempfile
from pathlib import Path

import yaml

from adarl.errors import AdaRLValueError
from adarl.runtime import metrics
from adarl.runtime.config import local_plugins
from adarl.runtime.run_folder.results import download_results, is_url, join, upload_tree, write_atomic
from adarl.runtime.run_folder.run_dir import RunDir

__all__ = [
    "FIGURE_FORMATS",
    "PAPER_RC",
    "check_formats",
    "save_figure",
    "paper_figure",
    "layer_styles",
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


#: the formats every report figure is written in, side by side (``<name>.png``, ``.pdf``, ``.svg``); the report's
#: Markdown and HTML link the PNG, a paper takes the PDF or SVG (vector, text kept as text)
FIGURE_FORMATS = ("png", "pdf", "svg")

#: a paper's widths, inches: one column (a single panel) and the full text width (panels side by side)
COLUMN_WIDTH = 3.4
PAGE_WIDTH = 7.0

#: what a single run's evaluation error bars are, in return.png's legend and report.md alike
EVAL_BARS = "evaluation on nominal dynamics: mean ± std over its episodes"

#: matplotlib settings of every report figure: text at 7-8 pt, legible at the printed size (``COLUMN_WIDTH`` for
#: one panel, ``PAGE_WIDTH`` for a row of panels, no scaling), constrained layout (long labels push the axes
#: instead of overlapping them), fonts embedded as TrueType in the PDF and kept as text in the SVG
PAPER_RC = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "legend.fontsize": 7,
    "legend.frameon": False,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "figure.titlesize": 8,
    "lines.linewidth": 1.2,
    "lines.markersize": 3,
    "axes.linewidth": 0.6,
    "grid.linewidth": 0.4,
    "grid.alpha": 0.3,
    "figure.constrained_layout.use": True,
    "savefig.dpi": 200,
    "pdf.fonttype": 42,
    "ps.fonttype": 42,
    "svg.fonttype": "none",
    "svg.hashsalt": "adarl",  # fixed ids: the same figure gives the same SVG bytes
}

# no creation date in the vector files: the same runs give the same bytes
_METADATA = {"png": {}, "pdf": {"CreationDate": None}, "svg": {"Date": None}}


def check_formats(formats) -> tuple[str, ...]:
    """``formats`` as a tuple, checked: distinct values of :data:`FIGURE_FORMATS`, ``png`` among them (the report
    links it); :class:`~adarl.errors.AdaRLValueError` names what is wrong and the allowed values."""
    given = (formats,) if isinstance(formats, str) else tuple(formats)
    bad = [f for f in given if f not in FIGURE_FORMATS]
    if bad or "png" not in given or len(set(given)) != len(given):
        why = f"unknown {bad}" if bad else "no 'png'" if "png" not in given else "a format repeated"
        raise AdaRLValueError(
            f"figure formats {list(given)}: {why}; allowed: a list of distinct values of {list(FIGURE_FORMATS)} "
            "with 'png' among them (the report links the PNG)"
        )
    return given


def paper_figure(nrows: int = 1, ncols: int = 1, *, width: float = COLUMN_WIDTH, height: float = 2.4, **kw):
    """A figure in :data:`PAPER_RC`'s style, ``width`` x ``height`` inches, and its axes (a 2-D array)."""
    plt = pyplot()
    with plt.rc_context(PAPER_RC):
        fig, axs = plt.subplots(nrows, ncols, figsize=(width, height), squeeze=False, **kw)
    fig.set_layout_engine("constrained")
    return fig, axs


def save_figure(fig, png: Path, formats=FIGURE_FORMATS) -> Path:
    """Write ``fig`` as ``png`` and beside it in the other ``formats`` (same stem), then close it; returns ``png``."""
    plt = pyplot()
    try:
        with plt.rc_context(PAPER_RC):
            for fmt in check_formats(formats):
                fig.savefig(png.with_suffix("." + fmt), format=fmt, metadata=_METADATA[fmt])
    finally:
        plt.close(fig)
    return png


def wrap_label(text: str, width: int = 40) -> str:
    """``text`` on lines of at most ``width`` characters, broken after a comma or at a space (a long setting such as
    ``variant=algorithm.lr=0.001,rank.beta=0.9`` stays readable in a title or legend instead of overflowing it)."""
    lines, line = [], ""
    for token in re.findall(r"[^,\s]+,?\s*|\s+", text):
        if line and len(line) + len(token.rstrip()) > width:
            lines.append(line.rstrip())
            line = ""
        line += token
    if line.strip():
        lines.append(line.rstrip())
    return "\n".join(lines)


def legend_below(fig, handles, labels, *, width: float) -> None:
    """One legend for the whole figure, below its axes (never over the data), as many columns as its widest label
    allows at ``width`` inches (about 17 characters an inch at 7 pt)."""
    if not handles:
        return
    chars = int(width * 17)
    labels = [wrap_label(lab, max(20, chars - 4)) for lab in labels]
    widest = max(len(line) for lab in labels for line in lab.split("\n")) + 5
    fig.legend(handles, labels, loc="outside lower center", ncols=max(1, min(len(labels), chars // widest)))


def figure_legend(fig, axs, *, width: float, extra: tuple = (), first: tuple = ()) -> None:
    """:func:`legend_below` with the labelled artists of ``axs`` (each label once, first seen), ``first``
    ``(handle, label)`` pairs before them and ``extra`` pairs after them."""
    seen: dict[str, object] = {}
    for h, lab in first:
        seen.setdefault(lab, h)
    for ax in axs:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    for h, lab in extra:
        seen.setdefault(lab, h)
    legend_below(fig, list(seen.values()), list(seen), width=width)


_LINESTYLES = ("-", "--", "-.", ":")
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*")
_LAYER_COLOURS = (0, 1, 2, 4, 5, 6, 8, 9, 7)  # tab10 without red, which marks the intrinsic rank and rank events


def layer_styles(names) -> dict[str, dict]:
    """Per layer, how a rank plot draws it: its own colour, line style and marker, and a line width that narrows
    from the first layer drawn to the last (each drawn above the one before), so that a layer at the same rank as
    another stays visible as a thin line inside the wider one rather than hidden behind it."""
    plt = pyplot()
    cmap = plt.get_cmap("tab10")
    names = list(dict.fromkeys(names))
    n = len(names)
    return {
        name: {
            "color": cmap(_LAYER_COLOURS[i % len(_LAYER_COLOURS)]),
            "ls": _LINESTYLES[i % len(_LINESTYLES)],
            "marker": _MARKERS[i % len(_MARKERS)],
            "lw": 0.8 + (1.8 * (n - 1 - i) / (n - 1) if n > 1 else 0.4),
            "ms": 2.5 + (2.0 * (n - 1 - i) / (n - 1) if n > 1 else 0.0),
            "zorder": 2 + i,
        }
        for i, name in enumerate(names)
    }


def paper_style(fn):
    """Draw ``fn``'s figure in :data:`PAPER_RC`'s style (font sizes are fixed when a text is made, so the whole
    drawing runs inside it)."""

    @functools.wraps(fn)
    def drawn(*args, **kwargs):
        with pyplot().rc_context(PAPER_RC):
            return fn(*args, **kwargs)

    return drawn


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


@paper_style
def plot_returns(run: RunDir, out: Path, formats=FIGURE_FORMATS) -> Path | None:
    """Training return (per finished episode batch) and evaluation mean ± std over its episodes, rank events
    marked; ``out`` (a PNG) and beside it the other ``formats``."""
    train = metrics.series(run.scalars(), metrics.TRAIN_RETURN)
    evals = run.read_eval()
    if not train and not evals:
        return None
    fig, axs = paper_figure(width=COLUMN_WIDTH, height=2.6)
    ax = axs[0, 0]
    if train:
        ax.plot([s for s, _ in train], [v for _, v in train], lw=0.8, alpha=0.6, label="training return (perturbed)")
    if evals:
        x = [int(r["frames"]) for r in evals]
        m = [float(r["mean"]) for r in evals]
        sd = [float(r["std"]) for r in evals]
        ax.errorbar(x, m, yerr=sd, fmt="o-", color="black", capsize=2, label=EVAL_BARS)
    for i, f in enumerate(_event_frames(run)):
        ax.axvline(f, color="red", ls="--", lw=0.8, label="rank event" if i == 0 else None)
    ax.set_xlabel("environment frames")
    ax.set_ylabel("episode return")
    ax.set_title(wrap_label(_title(run, "return"), 60))
    ax.grid(True)
    figure_legend(fig, [ax], width=COLUMN_WIDTH)
    return save_figure(fig, out, formats)


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


@paper_style
def plot_ranks(run: RunDir, out: Path, formats=FIGURE_FORMATS) -> Path | None:
    """Rank of each low-rank layer against environment frames, as ``return.png`` (a step plot through every
    event; older histories: :func:`rank_axis`); layers at the same rank stay visible (:func:`layer_styles`)."""
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
    fig, axs = paper_figure(width=COLUMN_WIDTH, height=2.6)
    ax = axs[0, 0]
    styles = layer_styles(series)
    for name, pts in series.items():
        if end > pts[-1][0]:
            pts = [*pts, (end, pts[-1][1])]
        ax.step([p[0] for p in pts], [p[1] for p in pts], where="post", label=name, **styles[name])
    ax.set_xlabel(label)
    ax.set_ylabel("rank")
    rank_ticks(ax, [p[1] for pts in series.values() for p in pts])
    ax.set_title(wrap_label(_title(run, "ranks"), 60))
    ax.grid(True)
    figure_legend(fig, [ax], width=COLUMN_WIDTH)
    return save_figure(fig, out, formats)


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


@paper_style
def plot_speed(run: RunDir, out: Path, formats=FIGURE_FORMATS) -> Path | None:
    """Optimisation steps per second against environment frames (``return.png``'s and ``ranks.png``'s axis), rank
    events as red dashed lines."""
    series = [(int(f), v) for f, v in metrics.series(run.scalars(), metrics.UPDATES_PER_S) if v > 0]
    if not series:
        return None
    fig, axs = paper_figure(width=COLUMN_WIDTH, height=2.4)
    ax = axs[0, 0]
    ax.plot([s for s, _ in series], [v for _, v in series], lw=1, marker=".", ms=3, label="updates/s")
    history = run.read_rank_history()
    label, xs, _ = rank_axis(run, history)
    if not label.startswith("environment frames"):  # nothing to place the events in frames with: left out
        xs = []
    for i, x in enumerate(sorted(set(xs))):
        ax.axvline(x, color="red", ls="--", lw=0.8, label="rank event" if i == 0 else None)
    ax.set_xlabel("environment frames")
    ax.set_ylabel("updates per second")
    ax.set_title(wrap_label(_title(run, "speed"), 60))
    ax.set_ylim(bottom=0)
    ax.grid(True)
    figure_legend(fig, [ax], width=COLUMN_WIDTH)
    return save_figure(fig, out, formats)


def write_report(path: str | os.PathLike, formats=FIGURE_FORMATS) -> Path | str:
    """Write ``report.md`` and ``plots/*.png`` (with each figure's other ``formats`` beside it: PDF and SVG by
    default) for the run folder at ``path``; returns the report's path.

    ``path`` may be an fsspec URL (:mod:`adarl.runtime.run_folder.results`): the report is made in a local copy of
    the run's files
    and
    uploaded beside them; the URL of ``report.md`` is returned."""
    if is_url(path):
        with tempfile.TemporaryDirectory(prefix="adarl-report-") as tmp:
            local = download_results(str(path), Path(tmp) / "run")
            md = write_report(local, formats)
            upload_tree(local / "plots", join(str(path), "plots"))
            write_atomic(join(str(path), "report.md"), md.read_bytes())
        return join(str(path), "report.md")
    formats = check_formats(formats)
    run = RunDir(path)
    local_plugins.check_recorded(run.plugin_modules(), str(run.path))  # changed: refused
    plots = run.path / "plots"
    plots.mkdir(exist_ok=True)
    ret = plot_returns(run, plots / "return.png", formats)
    rk = plot_ranks(run, plots / "ranks.png", formats)
    sp = plot_speed(run, plots / "speed.png", formats)
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
            f"Training return (perturbed) and {EVAL_BARS}; red dashed lines mark rank events.",
            "",
            "![return](plots/return.png)",
            "",
        ]
    if rk:
        lines += [
            "Rank per low-rank layer (each its own colour, line style and marker; a layer drawn first is wider, so "
            "that layers at the same rank both show).",
            "",
            "![ranks](plots/ranks.png)",
            "",
        ]
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
