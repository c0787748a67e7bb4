"""The report's figures: learning curves (with rank events and restarts marked), rank trajectories against
2*d_a+1, return against a numeric axis (Fig. 1) and robustness sweeps (Fig. 8). Each writes its PNG (matplotlib,
Agg) and the CSV it was drawn from. Private module of :mod:`adarl.experiments.report`.
"""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

from adarl.envs.registry import intrinsic_rank
from adarl.experiments.report._blocks import csv_text
from adarl.experiments.report._runs import Aggregate, Group, _num_key, _rank_series, rank_on_frames
from adarl.experiments.report.stats import interval_estimate, poi_estimate
from adarl.runtime.report import pyplot, rank_ticks


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
    """Nominal-dynamics evaluation vs frames: mean across seeds with its 95% bootstrap interval (a band of ± std
    over a few seeds says little about the mean); rank events dotted. The CSV keeps the std too."""
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
            ax.plot(xs, ms, "o-", ms=3, color=color, label=f"{_line_label(g, col_axis)} (n={len(g.scored)})")
            ax.fill_between(xs, los, his, color=color, alpha=0.15)
            for f in g.runs[0].events:
                ax.axvline(f, color=color, ls=":", lw=1)
        ax.set_title(title or "nominal-dynamics evaluation", fontsize=9)
        ax.set_xlabel("environment frames (evaluations binned by eval.interval)")
        ax.set_ylabel("nominal return (mean, 95% CI over seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2 if len(groups) > 6 else 1)
    fig.tight_layout()
    fig.savefig(out / "learning_curves.png", dpi=110)
    plt.close(fig)
    data = csv_text(rows, ["group", "frames", "mean", "std", "seeds", "mean_lo", "mean_hi"])
    (out / "learning_curves.csv").write_text(data)
    return out / "learning_curves.png", data


def plot_setting_curves(agg: Aggregate, out: Path) -> Path | None:
    """One panel per setting: every seed's nominal evaluations against frames (thin), their mean (bold), each
    seed's rank events or restarts (dotted verticals) and the setting's plateau threshold (dashed; one for every
    setting or its env's: ``agg.plateau_of``), so that what an event does to each run can be read off. Data:
    learning_curves_by_seed.csv."""
    groups = [g for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key]) if g.scored]
    if not groups:
        return None
    plt = pyplot()
    fig, axs = _subplots(plt, len(groups))
    cmap = plt.get_cmap("tab10")
    rows = []
    top = max(m for g in groups for r in g.scored for _, m in r.evals)
    for ax, g in zip(axs, groups):
        plateau = agg.plateau_of(g)  # the report's threshold for this setting (one, or its env's)
        for i, r in enumerate(g.scored):
            color = cmap(i % 10)
            ax.plot([f for f, _ in r.evals], [m for _, m in r.evals], "-", lw=0.8, alpha=0.7, color=color)
            for e in r.events:
                ax.axvline(e, color=color, ls=":", lw=0.8, alpha=0.6)
            rows += [[g.label, r.seed, f, m, "event" if f in r.events else ""] for f, m in r.evals]
            rows += [[g.label, r.seed, e, "", "event"] for e in r.events]
        frames = sorted({f for r in g.scored for f, _ in r.evals})
        means = [statistics.fmean([m for r in g.scored for ff, m in r.evals if ff == f]) for f in frames]
        ax.plot(frames, means, "k-", lw=2, label=f"mean of {len(g.scored)} seeds")
        if plateau is not None:
            ax.axhline(plateau, color="grey", ls="--", lw=1, label=f"plateau threshold {plateau:g}")
        ax.set_ylim(0, top * 1.05)
        ax.set_title(
            f"{g.label}: {g.plateau_count(plateau) if plateau is not None else len(g.scored)}"
            + (f"/{len(g.scored)} seeds above the plateau" if plateau is not None else " seeds"),
            fontsize=9,
        )
        ax.set_xlabel("frames (dotted: each seed's rank events / restarts)")
        ax.set_ylabel("nominal return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "learning_curves_by_seed.png", dpi=110)
    plt.close(fig)
    (out / "learning_curves_by_seed.csv").write_text(csv_text(rows, ["group", "seed", "frames", "mean", "event"]))
    return out / "learning_curves_by_seed.png"


def rank_x_label(agg: Aggregate) -> str:
    """The rank figure's x axis: environment frames when every run's events can be placed there, else (an older
    run folder among them) optimisation steps for all, so that the panels share one axis."""
    runs = [r for g in agg.groups for r in g.runs if r.rank_history]
    return "environment frames" if all(rank_on_frames(r) for r in runs) else "optimisation steps"


def plot_rank_trajectories(agg: Aggregate, out: Path) -> Path | None:
    """Rank of each low-rank layer against environment frames (the learning curves' axis), every seed, with the
    2*d_a+1 line (Fig. 4); on optimisation steps, said so on the axis and in ranks.csv, when some run's events
    cannot be placed in frames (an older run folder without the record)."""
    groups = [g for g in agg.groups if any(r.rank_history for r in g.runs)]
    if not groups:
        return None
    groups = groups[:12]
    frames = rank_x_label(agg) == "environment frames"
    plt = pyplot()
    fig, axs = _subplots(plt, len(groups))
    rows = []
    for ax, g in zip(axs, groups):
        colors: dict[str, object] = {}
        cmap = plt.get_cmap("tab10")
        for r in g.runs:
            for name, pts in _rank_series(r, frames=frames).items():
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
        rank_ticks(ax, [k for row in rows if row[0] == g.label for k in row[4:5]] + ([ref] if ref else []))
        ax.set_title(f"{g.label} ({len(g.runs)} seeds)", fontsize=9)
        ax.set_xlabel("environment frames" if frames else "optimisation steps")
        ax.set_ylabel("rank")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "ranks.png", dpi=110)
    plt.close(fig)
    (out / "ranks.csv").write_text(csv_text(rows, ["group", "seed", "layer", "frames" if frames else "step", "rank"]))
    return out / "ranks.png"


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
        gs = sorted((g for g in gs if g.scores), key=lambda g: float(dict(g.key)[axis]))
        x = [float(dict(g.key)[axis]) for g in gs]
        ax.errorbar(x, [g.mean for g in gs], yerr=[g.std for g in gs], fmt="o-", capsize=4, label=label or None)
        rows += [[label, dict(g.key)[axis], g.mean, g.std, len(g.scores), json.dumps(g.scores)] for g in gs]
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
    (out / f"return_vs_{axis}.csv").write_text(csv_text(rows, ["line", axis, "mean", "std", "seeds", "finals"]))
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
            ax.plot(xs, ws, ":", color=line.get_color(), lw=1)  # the worst episode at each grid point
            k = ws.index(min(ws))
            ax.plot([xs[k]], [ws[k]], "*", color="red", ms=12, zorder=5)  # the setting's worst case
            summary.append([g.label, len(results), statistics.fmean(ms), min(ms), min(ws)])
            ax.set_xlabel(param)
        ax.plot([], [], ":", color="grey", label="worst episode at each point")
        ax.plot([], [], "*", color="red", ms=12, label="worst case of a setting")
        ax.set_ylabel("return")
        ax.set_title(f"sweep {name}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"sweep_{name}.png", dpi=110)
        plt.close(fig)
        (out / f"sweep_{name}.csv").write_text(
            csv_text(rows, ["group", "param", "value", "mean", "std", "worst", "seeds"])
        )
        made.append((name, out / f"sweep_{name}.png", summary))
    return made


def plot_rliable(agg: Aggregate, out: Path, ref: str | None, col_axis: str | None) -> Path | None:
    """rliable's three figures (Agarwal et al. 2021) from the scores: interval estimates (mean and IQM with 95%
    stratified-bootstrap intervals per setting), the performance profile (the share of runs scoring above tau, with
    a bootstrap band) and, against the reference, the probability of improvement with its interval. Drawn with
    matplotlib from :mod:`adarl.experiments.report.stats` (rliable's estimators; the package itself is not needed).
    Data: rliable.csv."""
    groups = [g for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key]) if len(g.scores) >= 2]
    if not groups:
        return None
    plt = pyplot()
    others = [g for g in groups if ref is not None and col_axis is not None and dict(g.key).get(col_axis) != ref]
    refs = {
        tuple((a, v) for a, v in g.key if a != col_axis): g
        for g in groups
        if col_axis and dict(g.key).get(col_axis) == ref
    }
    pairs = [(refs.get(tuple((a, v) for a, v in g.key if a != col_axis)), g) for g in others]
    pairs = [(r, g) for r, g in pairs if r is not None]
    n = 3 if pairs else 2
    fig, axs = plt.subplots(1, n, figsize=(5.2 * n, 0.5 * len(groups) + 2.4), squeeze=False)
    axs = axs[0]
    rows = []
    labels = [g.label for g in groups]
    y = list(range(len(groups)))
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
            capsize=3,
            label=stat.upper() if j else "mean",
        )
        rows += [[g.label, stat, e[0], e[1], e[2]] for g, e in zip(groups, est)]
    axs[0].set_yticks(y, labels, fontsize=7)
    axs[0].set_xlabel("score (95% CI)")
    axs[0].set_title("interval estimates", fontsize=9)
    axs[0].legend(fontsize=7)
    axs[0].grid(alpha=0.3)
    everything = [s for g in groups for s in g.scores]
    taus = [min(everything) + (max(everything) - min(everything)) * k / 60 for k in range(61)]
    for g in groups:
        share = [sum(s > t for s in g.scores) / len(g.scores) for t in taus]
        axs[1].plot(taus, share, label=g.label)
        rows += [[g.label, "profile", t, v, ""] for t, v in zip(taus, share)]
    axs[1].set_xlabel("score threshold tau")
    axs[1].set_ylabel("share of runs with score > tau")
    axs[1].set_title("performance profile", fontsize=9)
    axs[1].legend(fontsize=7)
    axs[1].grid(alpha=0.3)
    if pairs:
        est = [poi_estimate(r.scores, g.scores) for r, g in pairs]
        pts = [e[0] for e in est]
        yy = list(range(len(pairs)))
        axs[2].errorbar(
            pts,
            yy,
            xerr=[[p - e[1] for p, e in zip(pts, est)], [e[2] - p for p, e in zip(pts, est)]],
            fmt="o",
            capsize=3,
        )
        axs[2].axvline(0.5, color="grey", ls="--", lw=1)
        axs[2].set_yticks(yy, [f"P({ref} > {dict(g.key)[col_axis]})" for _, g in pairs], fontsize=7)
        axs[2].set_xlim(0, 1)
        axs[2].set_xlabel("probability of improvement (95% CI)")
        axs[2].set_title("probability of improvement", fontsize=9)
        axs[2].grid(alpha=0.3)
        rows += [[g.label, f"P({ref} > setting)", e[0], e[1], e[2]] for (_, g), e in zip(pairs, est)]
    fig.tight_layout()
    fig.savefig(out / "rliable.png", dpi=110)
    plt.close(fig)
    (out / "rliable.csv").write_text(csv_text(rows, ["setting", "statistic", "value", "low", "high"]))
    return out / "rliable.png"


def plot_normalised_aggregate(
    estimates: dict[str, dict[str, tuple[float, float, float]]],
    taus,
    profiles: dict[str, tuple],
    out: Path,
    *,
    what: str = "normalised score",
) -> Path | None:
    """rliable's aggregate figures across tasks on normalised scores: per method (``estimates``: label -> {"mean",
    "iqm", "optimality_gap"} -> (point, low, high)) the three interval estimates, and the performance profile
    (``profiles``: label -> (share, low, high) at each of ``taus``) with its 95% band; dashed at 1 (the reference).
    Data: normalised_profile.csv (the interval estimates are the section's CSV)."""
    if not estimates:
        return None
    plt = pyplot()
    names = list(estimates)
    fig, axs = plt.subplots(
        1, 4, figsize=(17, 0.4 * len(names) + 2.8), squeeze=False, gridspec_kw={"width_ratios": [1, 1, 1, 1.7]}
    )
    axs = axs[0]
    cmap = plt.get_cmap("tab10")
    y = list(range(len(names)))[::-1]
    for ax, (stat, title) in zip(axs, (("mean", "mean"), ("iqm", "IQM"), ("optimality_gap", "optimality gap"))):
        for k, (name, yy) in enumerate(zip(names, y)):
            pt, lo, hi = estimates[name][stat]
            if math.isnan(pt):
                continue
            err = [[0.0], [0.0]] if math.isnan(lo) else [[pt - lo], [hi - pt]]
            ax.errorbar([pt], [yy], xerr=err, fmt="o", color=cmap(k % 10), capsize=3)
        ax.axvline(0.0 if stat == "optimality_gap" else 1.0, color="grey", ls="--", lw=1)
        ax.set_yticks(y, names if stat == "mean" else [""] * len(names), fontsize=7)
        ax.set_ylim(-0.5, len(names) - 0.5)
        ax.set_title(f"{title} (95% CI)", fontsize=9)
        ax.set_xlabel(what)
        ax.grid(alpha=0.3)
    rows = []
    for k, name in enumerate(names):
        share, lo, hi = profiles[name]
        line = axs[3].plot(taus, share, color=cmap(k % 10), label=name)[0]
        if not all(math.isnan(v) for v in lo):
            axs[3].fill_between(taus, lo, hi, color=line.get_color(), alpha=0.15)
        rows += [[name, t, s, a, b] for t, s, a, b in zip(taus, share, lo, hi)]
    axs[3].axvline(1.0, color="grey", ls="--", lw=1)
    axs[3].set_xlabel(f"{what} threshold tau")
    axs[3].set_ylabel("share of runs with score > tau")
    axs[3].set_title("performance profile (95% band)", fontsize=9)
    axs[3].legend(fontsize=7)
    axs[3].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "normalised_aggregate.png", dpi=110)
    plt.close(fig)
    (out / "normalised_profile.csv").write_text(csv_text(rows, ["method", "tau", "share", "low", "high"]))
    return out / "normalised_aggregate.png"
