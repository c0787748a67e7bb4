"""The report's figures: learning curves (with rank events and restarts marked), rank trajectories against
2*d_a+1, return against a numeric axis (Fig. 1) and robustness sweeps (Fig. 8). Each writes its PNG with a PDF and an
SVG beside it (the report option ``formats``; matplotlib, Agg) and the CSV it was drawn from, in the style every
report figure shares (:data:`adarl.runtime.report.PAPER_RC`: 7-8 pt text at a paper's widths, one panel
:data:`~adarl.runtime.report.COLUMN_WIDTH` wide, a row of panels :data:`~adarl.runtime.report.PAGE_WIDTH`, legends
below the axes, long titles wrapped). What a band or bar is is said once here (:data:`CI_BAND`, :data:`STD_BAND`) and
the figure's legend and the report's text both use it. Private module of :mod:`adarl.experiments.report`.
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

from adarl.envs.registry import intrinsic_rank
from adarl.experiments.report._blocks import csv_text
from adarl.experiments.report._runs import Aggregate, Group, _num_key, _rank_series, rank_on_frames
from adarl.experiments.report.stats import CONFIDENCE, REPS, interval_estimate, poi_estimate
from adarl.runtime.report import (
    COLUMN_WIDTH,
    FIGURE_FORMATS,
    PAGE_WIDTH,
    check_formats,
    figure_legend,
    layer_styles,
    paper_figure,
    paper_style,
    pyplot,
    rank_ticks,
    save_figure,
    wrap_label,
)

#: the learning curves' shaded band: in the figure's legend, the report's text and the docs, word for word
CI_BAND = f"shaded: {CONFIDENCE:.0%} bootstrap CI of the mean over seeds"
#: how that band is computed (the report's text and the docs add it to :data:`CI_BAND`)
CI_BAND_HOW = f"percentile interval of {REPS} resamples of the seeds; none with one seed"
#: the sweeps' shaded band and the return-vs-axis error bars (the sample std of the seeds' values)
STD_BAND = "shaded: ± 1 std over seeds"
STD_BARS = "error bars: ± 1 std over seeds"

PANEL_HEIGHT = 2.0  # inches a row of panels takes
LEGEND_HEIGHT = 0.5  # inches under the panels for the legend


def figure_formats(agg: Aggregate) -> tuple[str, ...]:
    """The formats the report writes each figure in: its ``formats`` option, else PNG, PDF and SVG."""
    return check_formats(agg.report.get("formats") or FIGURE_FORMATS)


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


def _subplots(n: int, *, legend_rows: int = 1):
    """``n`` panels, up to three a row, at a paper's width (one column for a single panel, the text width for
    more), with room below for the figure's legend; returns the figure, the panels and a title's width in
    characters."""
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    width = COLUMN_WIDTH if n == 1 else PAGE_WIDTH
    fig, axs = paper_figure(nrows, ncols, width=width, height=PANEL_HEIGHT * nrows + LEGEND_HEIGHT * legend_rows + 0.3)
    for ax in axs.flat[n:]:
        ax.set_visible(False)
    return fig, list(axs.flat[:n]), width, int(width / ncols * 15)


def _colours(n: int):
    """``n`` distinct colours (tab10 up to 10, tab20 up to 20, else viridis)."""
    plt = pyplot()
    if n <= 10:
        return [plt.get_cmap("tab10")(i) for i in range(n)]
    if n <= 20:
        return [plt.get_cmap("tab20")(i) for i in range(n)]
    return [plt.get_cmap("viridis")(i / (n - 1)) for i in range(n)]


def _proxy(**style):
    """A legend entry for something drawn without a label of its own (a band, the events' dotted lines)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if style.pop("patch", False):
        return Patch(**style)
    return Line2D([], [], **style)


@paper_style
def plot_learning_curves(agg: Aggregate, out: Path) -> tuple[Path | None, str]:
    """Nominal-dynamics evaluation vs frames: mean across seeds with its 95% bootstrap interval (:data:`CI_BAND`;
    a band of ± std over a few seeds says little about the mean); rank events dotted. The CSV keeps the std too."""
    col_axis, panels = _panels(agg)
    rows = []
    if not any(r.evals for g in agg.groups for r in g.runs):
        return None, ""
    labels = list(dict.fromkeys(_line_label(g, col_axis) for gs in panels.values() for g in gs))
    colour = dict(zip(labels, _colours(len(labels))))
    fig, axs, width, chars = _subplots(len(panels), legend_rows=1 + len(labels) // 3)
    for ax, (title, groups) in zip(axs, panels.items()):
        for g in groups:
            color = colour[_line_label(g, col_axis)]
            # Seeds evaluate at slightly different frames when warm-start frames count towards the budget: each
            # evaluation goes to the end of its eval.interval bin, so the seeds' curves line up.
            width_bin = int((g.runs[0].recipe.get("eval") or {}).get("interval") or 1)
            binned = [[(-(-ff // width_bin) * width_bin, m) for ff, m in r.evals] for r in g.scored]
            frames = sorted({f for ev in binned for f, _ in ev})
            xs, ms, los, his = [], [], [], []
            for f in frames:
                vals = [m for ev in binned for ff, m in ev if ff == f]
                mean, lo, hi = interval_estimate(vals, "mean")
                xs.append(f)
                ms.append(mean)
                los.append(mean if math.isnan(lo) else lo)
                his.append(mean if math.isnan(hi) else hi)
                sd = statistics.stdev(vals) if len(vals) > 1 else 0.0
                rows.append([g.label, f, mean, sd, len(vals), lo, hi])
            ax.plot(xs, ms, "o-", ms=2.5, color=color, label=f"{_line_label(g, col_axis)} (n={len(g.scored)})")
            ax.fill_between(xs, los, his, color=color, alpha=0.2, lw=0)
            for f in g.runs[0].events:
                ax.axvline(f, color=color, ls=":", lw=0.8)
        ax.set_title(wrap_label(title or "nominal-dynamics evaluation", chars))
        ax.set_xlabel("environment frames")
        ax.set_ylabel("mean nominal return")
        ax.grid(True)
    extra = [
        (_proxy(patch=True, color="grey", alpha=0.3, lw=0), CI_BAND),
        (_proxy(color="grey", ls=":", lw=0.8), "dotted: rank events / restarts (first seed)"),
    ]
    figure_legend(fig, axs, width=width, extra=extra)
    save_figure(fig, out / "learning_curves.png", figure_formats(agg))
    data = csv_text(rows, ["group", "frames", "mean", "std", "seeds", "mean_lo", "mean_hi"])
    (out / "learning_curves.csv").write_text(data)
    return out / "learning_curves.png", data


@paper_style
def plot_setting_curves(agg: Aggregate, out: Path) -> Path | None:
    """One panel per setting: every seed's nominal evaluations against frames (thin, one colour per seed, the same
    in every panel and named in the legend), their mean (bold), each seed's rank events or restarts (dotted
    verticals) and the setting's plateau threshold (dashed; one for every setting or its env's:
    ``agg.plateau_of``), so that what an event does to each run can be read off. Data:
    learning_curves_by_seed.csv."""
    groups = [g for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key]) if g.scored]
    if not groups:
        return None
    seeds = sorted({r.seed for g in groups for r in g.scored})
    colour = dict(zip(seeds, _colours(len(seeds))))
    fig, axs, width, chars = _subplots(len(groups), legend_rows=1 + len(seeds) // 6)
    rows = []
    top = max(m for g in groups for r in g.scored for _, m in r.evals)
    for ax, g in zip(axs, groups):
        plateau = agg.plateau_of(g)  # the report's threshold for this setting (one, or its env's)
        for r in g.scored:
            color = colour[r.seed]
            ax.plot(
                [f for f, _ in r.evals], [m for _, m in r.evals], "-", lw=0.8, alpha=0.8, color=color,
                label=f"seed {r.seed}",
            )  # fmt: skip
            for e in r.events:
                ax.axvline(e, color=color, ls=":", lw=0.7, alpha=0.6)
            rows += [[g.label, r.seed, f, m, "event" if f in r.events else ""] for f, m in r.evals]
            rows += [[g.label, r.seed, e, "", "event"] for e in r.events]
        frames = sorted({f for r in g.scored for f, _ in r.evals})
        means = [statistics.fmean([m for r in g.scored for ff, m in r.evals if ff == f]) for f in frames]
        if len(g.scored) > 1:  # one seed's mean is its own curve: not drawn over it
            ax.plot(frames, means, "k-", lw=1.8, label="mean of the seeds")
        if plateau is not None:
            ax.axhline(plateau, color="grey", ls="--", lw=0.8, label="plateau threshold")
        ax.set_ylim(0, top * 1.05)
        count = (
            f"{g.plateau_count(plateau)}/{len(g.scored)} seeds above {plateau:g}"
            if plateau is not None
            else f"{len(g.scored)} seeds"
        )
        ax.set_title(wrap_label(f"{g.label}: {count}", chars))
        ax.set_xlabel("environment frames")
        ax.set_ylabel("nominal return")
        ax.grid(True)
    named = [(_proxy(color=colour[s], lw=0.8), f"seed {s}") for s in seeds]  # in the seeds' order
    extra = [(_proxy(color="grey", ls=":", lw=0.8), "dotted: the seed's rank events / restarts")]
    figure_legend(fig, axs, width=width, extra=extra, first=named)
    save_figure(fig, out / "learning_curves_by_seed.png", figure_formats(agg))
    (out / "learning_curves_by_seed.csv").write_text(csv_text(rows, ["group", "seed", "frames", "mean", "event"]))
    return out / "learning_curves_by_seed.png"


def rank_x_label(agg: Aggregate) -> str:
    """The rank figure's x axis: environment frames when every run's events can be placed there, else (an older
    run folder among them) optimisation steps for all, so that the panels share one axis."""
    runs = [r for g in agg.groups for r in g.runs if r.rank_history]
    return "environment frames" if all(rank_on_frames(r) for r in runs) else "optimisation steps"


@paper_style
def plot_rank_trajectories(agg: Aggregate, out: Path) -> Path | None:
    """Rank of each low-rank layer against environment frames (the learning curves' axis), every seed, with the
    2*d_a+1 line (Fig. 4); on optimisation steps, said so on the axis and in ranks.csv, when some run's events
    cannot be placed in frames (an older run folder without the record). Each layer has its own colour, line
    style and marker, the same in every panel and named once in the legend, and the layers drawn first are wider
    (:func:`~adarl.runtime.report.layer_styles`): two layers at the same rank both stay visible."""
    groups = [g for g in agg.groups if any(r.rank_history for r in g.runs)]
    if not groups:
        return None
    groups = groups[:12]
    frames = rank_x_label(agg) == "environment frames"
    series = {(id(g), id(r)): _rank_series(r, frames=frames) for g in groups for r in g.runs}
    styles = layer_styles(name for s in series.values() for name in s)
    fig, axs, width, chars = _subplots(len(groups), legend_rows=1 + len(styles) // 4)
    rows = []
    for ax, g in zip(axs, groups):
        for r in g.runs:
            for name, pts in series[(id(g), id(r))].items():
                ax.step(
                    [p[0] for p in pts],
                    [p[1] for p in pts],
                    where="post",
                    alpha=0.8,
                    label=name,
                    **styles[name],
                )
                rows += [[g.label, r.seed, name, s, k] for s, k in pts]
        ref = agg.report.get("intrinsic_rank") or intrinsic_rank(g.runs[0].env_id)
        if ref:
            ax.axhline(ref, color="red", ls="--", lw=0.8, zorder=1, label=f"intrinsic rank {ref}")
        rank_ticks(ax, [k for row in rows if row[0] == g.label for k in row[4:5]] + ([ref] if ref else []))
        ax.set_title(wrap_label(f"{g.label} ({len(g.runs)} seeds)", chars))
        ax.set_xlabel("environment frames" if frames else "optimisation steps")
        ax.set_ylabel("rank")
        ax.grid(True)
    figure_legend(fig, axs, width=width)
    save_figure(fig, out / "ranks.png", figure_formats(agg))
    (out / "ranks.csv").write_text(csv_text(rows, ["group", "seed", "layer", "frames" if frames else "step", "rank"]))
    return out / "ranks.png"


@paper_style
def plot_return_vs(agg: Aggregate, axis: str, out: Path) -> Path | None:
    """Final return (mean across seeds with :data:`STD_BARS`) against a numeric axis such as the rank (Fig. 1)."""
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
    fig, axs = paper_figure(width=COLUMN_WIDTH, height=2.4 + LEGEND_HEIGHT * (1 + len(lines) // 2))
    ax = axs[0, 0]
    rows = []
    for label, gs in lines.items():
        gs = sorted((g for g in gs if g.scores), key=lambda g: float(dict(g.key)[axis]))
        x = [float(dict(g.key)[axis]) for g in gs]
        ax.errorbar(x, [g.mean for g in gs], yerr=[g.std for g in gs], fmt="o-", capsize=2, label=label or None)
        rows += [[label, dict(g.key)[axis], g.mean, g.std, len(g.scores), json.dumps(g.scores)] for g in gs]
    ref = agg.report.get("intrinsic_rank")
    if ref and axis == "rank":
        ax.axvline(ref, color="red", ls="--", lw=0.8, label=f"intrinsic rank {ref}")
    ax.set_xlabel(axis)
    ax.set_ylabel("final nominal return (mean over seeds)")
    ax.grid(True)
    figure_legend(fig, [ax], width=COLUMN_WIDTH, extra=[(_proxy(color="black", marker="|", ls=""), STD_BARS)])
    save_figure(fig, out / f"return_vs_{axis}.png", figure_formats(agg))
    (out / f"return_vs_{axis}.csv").write_text(csv_text(rows, ["line", axis, "mean", "std", "seeds", "finals"]))
    return out / f"return_vs_{axis}.png"


@paper_style
def plot_sweeps(agg: Aggregate, out: Path) -> list[tuple[str, Path, list[list]]]:
    """Per 1-D sweep name: mean across seeds of each grid point's mean with :data:`STD_BAND`, the worst episode at
    each point (dotted), red stars at each setting's worst case."""
    names = sorted({n for g in agg.groups for r in g.runs for n, s in r.sweeps.items() if len(s.params) == 1})
    made = []
    for name in names:
        drawn = [
            g
            for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])
            if any(name in r.sweeps for r in g.runs)
        ]
        fig, axs = paper_figure(width=COLUMN_WIDTH, height=2.4 + LEGEND_HEIGHT * (1 + len(drawn) // 2))
        ax = axs[0, 0]
        rows, summary = [], []
        for g in drawn:
            results = [r.sweeps[name] for r in g.runs if name in r.sweeps]
            param = results[0].params[0]
            xs = [p.values[param] for p in results[0].points]
            ms, ss, ws = [], [], []
            for i, _ in enumerate(xs):
                vals = [res.points[i].mean for res in results]
                ms.append(statistics.fmean(vals))
                ss.append(statistics.stdev(vals) if len(vals) > 1 else 0.0)
                ws.append(min(res.points[i].worst for res in results))
                rows.append([g.label, param, xs[i], ms[-1], ss[-1], ws[-1], len(vals)])
            line = ax.plot(xs, ms, "o-", ms=2.5, label=g.label)[0]
            ax.fill_between(
                xs,
                [m - s for m, s in zip(ms, ss)],
                [m + s for m, s in zip(ms, ss)],
                color=line.get_color(),
                alpha=0.2,
                lw=0,
            )
            ax.plot(xs, ws, ":", color=line.get_color(), lw=0.8)  # the worst episode at each grid point
            k = ws.index(min(ws))
            ax.plot([xs[k]], [ws[k]], "*", color="red", ms=8, zorder=5)  # the setting's worst case
            summary.append([g.label, len(results), statistics.fmean(ms), min(ms), min(ws)])
            ax.set_xlabel(param)
        extra = [
            (_proxy(patch=True, color="grey", alpha=0.3, lw=0), STD_BAND),
            (_proxy(color="grey", ls=":", lw=0.8), "dotted: worst episode at each point"),
            (_proxy(color="red", marker="*", ls="", ms=8), "worst case of a setting"),
        ]
        ax.set_ylabel("return (mean over seeds)")
        ax.set_title(wrap_label(f"sweep {name}", 50))
        ax.grid(True)
        figure_legend(fig, [ax], width=COLUMN_WIDTH, extra=extra)
        save_figure(fig, out / f"sweep_{name}.png", figure_formats(agg))
        (out / f"sweep_{name}.csv").write_text(
            csv_text(rows, ["group", "param", "value", "mean", "std", "worst", "seeds"])
        )
        made.append((name, out / f"sweep_{name}.png", summary))
    return made


@paper_style
def plot_rliable(agg: Aggregate, out: Path, ref: str | None, col_axis: str | None) -> Path | None:
    """rliable's three figures (Agarwal et al. 2021) from the scores: interval estimates (mean and IQM with 95%
    stratified-bootstrap intervals per setting), the performance profile (the share of runs scoring above tau)
    and, against the reference, the probability of improvement with its interval. Drawn with matplotlib from
    :mod:`adarl.experiments.report.stats` (rliable's estimators; the package itself is not needed).
    Data: rliable.csv."""
    groups = [g for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key]) if len(g.scores) >= 2]
    if not groups:
        return None
    others = [g for g in groups if ref is not None and col_axis is not None and dict(g.key).get(col_axis) != ref]
    refs = {
        tuple((a, v) for a, v in g.key if a != col_axis): g
        for g in groups
        if col_axis and dict(g.key).get(col_axis) == ref
    }
    pairs = [(refs.get(tuple((a, v) for a, v in g.key if a != col_axis)), g) for g in others]
    pairs = [(r, g) for r, g in pairs if r is not None]
    n = 3 if pairs else 2
    fig, axs = paper_figure(
        1, n, width=PAGE_WIDTH, height=0.3 * len(groups) + 1.6 + LEGEND_HEIGHT * (1 + len(groups) // 3)
    )
    axs = axs[0]
    rows = []
    labels = [wrap_label(g.label, 28) for g in groups]
    y = list(range(len(groups)))
    colours = _colours(len(groups))
    for j, stat in enumerate(("mean", "iqm")):
        est = [interval_estimate(g.scores, stat) for g in groups]
        pts = [e[0] for e in est]
        lo = [p - e[1] for p, e in zip(pts, est)]
        hi = [e[2] - p for p, e in zip(pts, est)]
        axs[0].errorbar(
            pts,
            [v + (0.15 if j else -0.15) for v in y],
            xerr=[lo, hi],
            fmt="o" if j else "s",
            color="black" if j else "grey",
            capsize=2,
            label=stat.upper() if j else "mean",
        )
        rows += [[g.label, stat, e[0], e[1], e[2]] for g, e in zip(groups, est)]
    axs[0].set_yticks(y, labels)
    axs[0].set_xlabel(f"score ({CONFIDENCE:.0%} bootstrap CI)")
    axs[0].set_title("interval estimates")
    axs[0].legend(loc="best")
    axs[0].grid(True)
    everything = [s for g in groups for s in g.scores]
    taus = [min(everything) + (max(everything) - min(everything)) * k / 60 for k in range(61)]
    for g, c in zip(groups, colours):
        share = [sum(s > t for s in g.scores) / len(g.scores) for t in taus]
        axs[1].plot(taus, share, color=c, label=g.label)
        rows += [[g.label, "profile", t, v, ""] for t, v in zip(taus, share)]
    axs[1].set_xlabel("score threshold tau")
    axs[1].set_ylabel("share of runs with score > tau")
    axs[1].set_title("performance profile")
    axs[1].grid(True)
    if pairs:
        est = [poi_estimate(r.scores, g.scores) for r, g in pairs]
        pts = [e[0] for e in est]
        yy = list(range(len(pairs)))
        axs[2].errorbar(
            pts,
            yy,
            xerr=[[p - e[1] for p, e in zip(pts, est)], [e[2] - p for p, e in zip(pts, est)]],
            fmt="o",
            color="black",
            capsize=2,
        )
        axs[2].axvline(0.5, color="grey", ls="--", lw=0.8)
        axs[2].set_yticks(yy, [wrap_label(f"P({ref} > {dict(g.key)[col_axis]})", 28) for _, g in pairs])
        axs[2].set_xlim(0, 1)
        axs[2].set_xlabel(f"probability of improvement ({CONFIDENCE:.0%} bootstrap CI)")
        axs[2].set_title("probability of improvement")
        axs[2].grid(True)
        rows += [[g.label, f"P({ref} > setting)", e[0], e[1], e[2]] for (_, g), e in zip(pairs, est)]
    figure_legend(fig, [axs[1]], width=PAGE_WIDTH)
    save_figure(fig, out / "rliable.png", figure_formats(agg))
    (out / "rliable.csv").write_text(csv_text(rows, ["setting", "statistic", "value", "low", "high"]))
    return out / "rliable.png"


@paper_style
def plot_normalised_aggregate(
    estimates: dict[str, dict[str, tuple[float, float, float]]],
    taus,
    profiles: dict[str, tuple],
    out: Path,
    *,
    what: str = "normalised score",
    formats=FIGURE_FORMATS,
) -> Path | None:
    """rliable's aggregate figures across tasks on normalised scores: per method (``estimates``: label -> {"mean",
    "iqm", "optimality_gap"} -> (point, low, high)) the three interval estimates, and the performance profile
    (``profiles``: label -> (share, low, high) at each of ``taus``) with its 95% band; dashed at 1 (the reference).
    Data: normalised_profile.csv (the interval estimates are the section's CSV)."""
    if not estimates:
        return None
    names = list(estimates)
    fig, axs = paper_figure(
        1,
        4,
        width=PAGE_WIDTH,
        height=0.3 * len(names) + 1.7 + LEGEND_HEIGHT * (1 + len(names) // 4),
        gridspec_kw={"width_ratios": [1, 1, 1, 1.7]},
    )
    axs = axs[0]
    colours = _colours(len(names))
    y = list(range(len(names)))[::-1]
    for ax, (stat, title) in zip(axs, (("mean", "mean"), ("iqm", "IQM"), ("optimality_gap", "optimality gap"))):
        for k, (name, yy) in enumerate(zip(names, y)):
            pt, lo, hi = estimates[name][stat]
            if math.isnan(pt):
                continue
            err = [[0.0], [0.0]] if math.isnan(lo) else [[pt - lo], [hi - pt]]
            ax.errorbar([pt], [yy], xerr=err, fmt="o", color=colours[k], capsize=2)
        ax.axvline(0.0 if stat == "optimality_gap" else 1.0, color="grey", ls="--", lw=0.8)
        ax.set_yticks(y, [wrap_label(n, 20) for n in names] if stat == "mean" else [""] * len(names))
        ax.set_ylim(-0.5, len(names) - 0.5)
        ax.set_title(f"{title} ({CONFIDENCE:.0%} CI)")
        ax.set_xlabel(what)
        ax.grid(True)
    rows = []
    for k, name in enumerate(names):
        share, lo, hi = profiles[name]
        line = axs[3].plot(taus, share, color=colours[k], label=name)[0]
        if not all(math.isnan(v) for v in lo):
            axs[3].fill_between(taus, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
        rows += [[name, t, s, a, b] for t, s, a, b in zip(taus, share, lo, hi)]
    axs[3].axvline(1.0, color="grey", ls="--", lw=0.8)
    axs[3].set_xlabel(f"{what} threshold tau")
    axs[3].set_ylabel("share of runs with score > tau")
    axs[3].set_title(f"performance profile ({CONFIDENCE:.0%} band)")
    axs[3].grid(True)
    figure_legend(fig, [axs[3]], width=PAGE_WIDTH)
    save_figure(fig, out / "normalised_aggregate.png", formats)
    (out / "normalised_profile.csv").write_text(csv_text(rows, ["method", "tau", "share", "low", "high"]))
    return out / "normalised_aggregate.png"
