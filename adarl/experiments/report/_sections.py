"""The report's sections: the score table, statistics across seeds with the decision rule's verdict, the plateau
count, scores at given optimisation steps, the training return around rank events (Fig. 9) and the rank settling
table (Fig. 4). Each returns its blocks (:mod:`adarl.experiments.report._blocks`) and writes the CSV it was computed
from. Private module of :mod:`adarl.experiments.report`.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from adarl.envs.registry import intrinsic_rank
from adarl.experiments.report._blocks import Block, Heading, Paragraph, Table, csv_text
from adarl.experiments.report._runs import Aggregate, Group, _num_key, event_dips, rank_settling
from adarl.experiments.report.stats import interval_estimate, poi_estimate


def _cell(g: Group | None) -> str:
    if g is None or not g.scores:
        return "–"
    return f"{g.mean:.1f} ± {g.std:.1f} (n={len(g.scores)})"


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
            means = [g.mean if g is not None and g.scores else -math.inf for g in gs]
            if max(means) > -math.inf:
                bold.append((i, 1 + means.index(max(means))))
        return header, rows, bold
    groups = sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])
    header = [" / ".join(agg.axes) or "runs", "final return (mean ± std across seeds)", "seeds"]
    rows = [[", ".join(v for _, v in g.key) or "all", _cell(g), ",".join(map(str, g.seeds))] for g in groups]
    means = [g.mean if g.scores else -math.inf for g in groups]
    bold = [(means.index(max(means)), 1)] if means and max(means) > -math.inf else []
    return header, rows, bold


def _rank_settling_blocks(agg: Aggregate, out: Path) -> list[Block]:
    groups = [
        g
        for g in sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])
        if any(r.rank_history for r in g.scored)
    ]
    rows, crow, rule_rows = [], [], []
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
                        d.get("last_candidate"),
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
                    ", ".join("–" if d.get("last_candidate") is None else str(d["last_candidate"]) for _, d in ds),
                ]
            )
            ref = agg.report.get("intrinsic_rank") or intrinsic_rank(g.runs[0].env_id)
            finals = [d["final"] for _, d in ds]
            settled = sum(1 for _, d in ds if d["events_after"] >= 1)
            med = statistics.median(finals)
            near = ref is not None and abs(med - ref) <= 1
            rule_rows.append(
                [
                    g.label,
                    name,
                    f"{med:g}",
                    "–" if ref is None else str(ref),
                    f"{settled}/{len(ds)}",
                    "–" if ref is None else ("yes" if near and 2 * settled >= len(ds) else "no"),
                ]
            )
    if not rows:
        return []
    (out / "rank_settling.csv").write_text(
        csv_text(
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
                "last_candidate",
            ],
        )
    )
    return [
        Heading(2, "Do the ranks settle?"),
        Paragraph(
            "Per layer, one value per seed (seeds in increasing order): the final rank, the smallest rank it "
            "reached, the optimisation step of its last change, the number of rank events after that change that "
            "left it unchanged, and the rule's own candidate at the last event (Eq. 10's proposal before the "
            "acceptance step, which keeps the rank when the truncated network's outputs move beyond the "
            "tolerance). Data in rank_settling.csv."
        ),
        Table(
            [
                "setting",
                "layer",
                "initial",
                "final rank",
                "lowest rank",
                "last change at step",
                "events since",
                "rule's candidate at the last event",
            ],
            rows,
        ),
        Paragraph(
            "Against 2·d_a+1 (Tiwari et al.'s intrinsic rank; paper Fig. 4): the median final rank over seeds, "
            "the seeds whose rank the last event left unchanged, and whether the layer meets the protocol's rule "
            "(unchanged over the last event in at least half the seeds, median within ±1 of 2·d_a+1)."
        ),
        Table(
            ["setting", "layer", "median final rank", "2·d_a+1", "unchanged at the last event", "rule met"], rule_rows
        ),
    ]


def _ci(point: float, lo: float, hi: float) -> str:
    if math.isnan(point):
        return "–"
    return f"{point:.1f} [{lo:.1f}, {hi:.1f}]" if not math.isnan(lo) else f"{point:.1f}"


def verdict(
    poi: tuple[float, float, float],
    a: str,
    b: str,
    seeds: tuple[int, int] = (0, 0),
    need: int | dict[str, int] | None = None,
) -> str:
    """The protocol's decision rule on P(a > b) [low, high]: a side beats the other only when the 95% interval
    excludes 0.5 (docs/reproduction.md); none while a side has fewer ``seeds`` than ``need`` plans for it (one
    count for both, or a count per arm)."""
    _, low, high = poi
    if math.isnan(low) or math.isnan(high):
        return "–"
    if need is not None:
        planned = (need[a], need[b]) if isinstance(need, dict) else (need, need)
        if seeds[0] < planned[0] or seeds[1] < planned[1]:
            each = f"{planned[0]} seeds each" if planned[0] == planned[1] else f"{planned[0]} and {planned[1]} seeds"
            return f"waits for {each} (has {seeds[0]} and {seeds[1]})"
    if low > 0.5:
        return f"{a} beats {b}"
    if high < 0.5:
        return f"{b} beats {a}"
    return "no difference shown"


def _planned_seeds(need: int | dict[str, int]) -> str:
    if isinstance(need, dict):
        return "their planned seeds (" + ", ".join(f"{k} {v}" for k, v in need.items()) + ")"
    return f"{need} seeds"


def _statistics_blocks(agg: Aggregate, out: Path) -> list[Block]:
    """IQM and mean with stratified bootstrap intervals, probability of improvement over the reference column,
    and scores at the optimisation steps the spec names (adarl.experiments.report.stats); writes statistics.csv."""
    col_axis = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    ref = agg.report.get("reference")
    groups = sorted(agg.groups, key=lambda g: [_num_key(v) for _, v in g.key])

    def _seed_counts(gs) -> str:
        ns = sorted({len(g.scores) for g in gs if g.scores})
        if not ns:
            return "no finished seeds"
        n = f"{ns[0]}" if len(ns) == 1 else f"{ns[0]}-{ns[-1]}"
        return f"{n} seed{'s' if ns[-1] > 1 else ''} per setting"

    def partner(g: Group) -> Group | None:
        if ref is None or col_axis is None or dict(g.key).get(col_axis) == ref:
            return None
        want = {**dict(g.key), col_axis: ref}
        return next((h for h in agg.groups if dict(h.key) == want), None)

    plateau, need = agg.report.get("plateau"), agg.report.get("verdict_seeds")
    per_value = isinstance(plateau, dict)  # one threshold per value of an axis (each env's stand-still + 500)
    header = ["setting", "n", "mean ± std", "mean [95% CI]", "IQM [95% CI]"]
    if plateau is not None:
        header.append("seeds with best eval > its plateau" if per_value else f"seeds with best eval > {plateau:g}")
    if ref is not None:
        header += [f"P({ref} > setting) [95% CI]", "verdict (95% interval against 0.5)"]
    rows, csv_rows = [], []
    for g in groups:
        f = g.scores
        m = interval_estimate(f, "mean")
        q = interval_estimate(f, "iqm")
        row = [g.label, str(len(f)), f"{g.mean:.1f} ± {g.std:.1f}" if f else "–", _ci(*m), _ci(*q)]
        threshold = agg.plateau_of(g)
        if plateau is not None:
            row.append(
                "–"
                if threshold is None
                else f"{g.plateau_count(threshold)}/{len(f)}" + (f" (> {threshold:g})" if per_value else "")
            )
        p, said = (math.nan,) * 3, ""
        h = partner(g)
        if ref is not None:
            if h is not None and h.scores and f:
                p = poi_estimate(h.scores, f)
                said = verdict(p, ref, dict(g.key)[col_axis], (len(h.scores), len(f)), need)
                row += [f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]", said]
            else:
                row += ["–", "–"]
        rows.append(row)
        csv_rows.append(
            [
                *[v for _, v in g.key],
                len(f),
                g.mean,
                g.std,
                *m,
                *q,
                *p,
                g.plateau_count(threshold) if threshold is not None else "",
                "" if threshold is None else threshold,
                g.score_last,
                said,
            ]
        )
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
        "above_plateau",
        "plateau",
        "score_last",
        "verdict",  # the decision rule's words against the reference, as in the table ("" for the reference)
    ]
    (out / "statistics.csv").write_text(csv_text(csv_rows, names))
    blocks: list[Block] = [
        Heading(2, "Statistics across seeds"),
        Paragraph(
            "Each seed counted once. Mean and interquartile mean (IQM: the mean of the middle 50% of the seeds' "
            "scores) with 95% stratified-bootstrap percentile intervals (2000 resamples of the seeds within each "
            "env, fixed seed), computed by adarl.experiments.report.stats as the rliable library defines them"
            + (
                f"; P({ref} > setting): the probability that a run of {ref} scores above a run of the setting "
                "(ties count half), with its bootstrap interval, and the verdict it gives: one side 'beats' the "
                "other when the interval excludes 0.5, else 'no difference shown'"
                + (
                    f", and only once both sides have {_planned_seeds(need)} (the count planned; before, P is interim)"
                    if need
                    else ""
                )
                if ref is not None
                else ""
            )
            + (
                "; seeds with best eval > its plateau: the runs whose best nominal evaluation exceeds the threshold of "
                "their " + ", ".join(f"{k} ({v:g})" for k, v in plateau.items())
                if per_value
                else f"; seeds with best eval > {plateau:g}: the runs whose best nominal evaluation exceeds the "
                "plateau threshold"
                if plateau is not None
                else ""
            )
            + f". With {_seed_counts(groups)} the intervals are wide. Data in statistics.csv.",
        ),
        Table(header, rows),
    ]
    pairs = [tuple(pair) for pair in agg.report.get("pairs") or []]
    if pairs:
        blocks += _pair_blocks(agg, groups, col_axis, pairs, out)
    dups = [f"{g.label}: seeds {g.duplicate_seeds}" for g in groups if g.duplicate_seeds]
    if dups:
        blocks.append(Paragraph("Seeds found more than once (counted once, the first run found): " + "; ".join(dups)))
    window = agg.report.get("event_window")
    if window:
        blocks += _event_window_blocks(groups, int(window), out, col_axis=col_axis, ref=ref, need=need)
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
            csv_text(crow, [*agg.axes, "updates", "n_seeds", "mean", "std", "iqm", "iqm_lo", "iqm_hi"])
        )
        blocks += [
            Heading(2, "Score at the end of each iteration"),
            Paragraph(
                "Each run's first nominal-dynamics evaluation at or after the given number of optimisation "
                "steps: mean ± std across seeds; IQM [95% CI]. Data in at_updates.csv."
            ),
            Table(head, trows),
        ]
    return blocks


def _pair_blocks(
    agg: Aggregate, groups: list[Group], col_axis: str | None, pairs: list[tuple[str, str]], out: Path
) -> list[Block]:
    """``report.pairs``: P(a > b) for two values of the column axis, per setting of the other axes, with the
    decision rule's verdict (what one control isolates from another); writes pairs.csv."""
    if col_axis is None:
        return [Paragraph(f"report.pairs {pairs} needs a column axis (report.columns); none in {agg.axes}.")]
    row_axes = [a for a in agg.axes if a != col_axis]
    by = {(tuple(dict(g.key)[a] for a in row_axes), dict(g.key)[col_axis]): g for g in groups}
    row_keys = sorted({k for k, _ in by}, key=lambda t: [_num_key(x) for x in t])
    rows, crow = [], []
    for a, b in pairs:
        for rk in row_keys:
            ga, gb = by.get((rk, a)), by.get((rk, b))
            label = ", ".join(f"{k}={v}" for k, v in zip(row_axes, rk))
            if ga is None or gb is None or not ga.scores or not gb.scores:
                missing = " and ".join(v for v, g in ((a, ga), (b, gb)) if g is None or not g.scores)
                rows.append([label, f"P({a} > {b})", "–", "–", f"no finished runs of {missing}"])
                counts = [0 if g is None else len(g.scores) for g in (ga, gb)]
                crow.append([*rk, a, b, *counts, "", "", "", f"no finished runs of {missing}"])
                continue
            p = poi_estimate(ga.scores, gb.scores)
            said = verdict(p, a, b, (len(ga.scores), len(gb.scores)), agg.report.get("verdict_seeds"))
            rows.append(
                [
                    label,
                    f"P({a} > {b})",
                    f"{len(ga.scores)} vs {len(gb.scores)}",
                    f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]",
                    said,
                ]
            )
            crow.append([*rk, a, b, len(ga.scores), len(gb.scores), *p, said])
    (out / "pairs.csv").write_text(
        csv_text(crow, [*row_axes, "a", "b", "n_a", "n_b", "poi", "poi_lo", "poi_hi", "verdict"])
    )
    return [
        Heading(2, "Pairwise comparisons"),
        Paragraph(
            "report.pairs: for two values a and b of the column axis, the probability that a run of a "
            "scores above a run of b (ties count half; each seed once) with its 95% stratified-bootstrap interval, "
            "and the decision rule's verdict. Data in pairs.csv."
        ),
        Table(["setting", "comparison", "seeds", "P [95% CI]", "verdict (95% interval against 0.5)"], rows),
    ]


def _event_window_blocks(
    groups: list[Group],
    window: int,
    out: Path,
    *,
    col_axis: str | None = None,
    ref: str | None = None,
    need: int | dict[str, int] | None = None,
) -> list[Block]:
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
        header += [f"P({ref} dips less) [95% CI]", "verdict (95% interval against 0.5)"]
    table = []
    for g, row in rows:
        if with_ref:
            key = dict(g.key)
            ref_key = tuple((a, ref if a == col_axis else v) for a, v in g.key)
            if key.get(col_axis) != ref and ref_key in per_seed:
                p = poi_estimate(per_seed[ref_key], per_seed[g.key])
                counts = (len(per_seed[ref_key]), len(per_seed[g.key]))
                row += [f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]", verdict(p, ref, key[col_axis], counts, need)]
            else:
                row += ["–", "–"]
        table.append(row)
    (out / "event_window.csv").write_text(
        csv_text(crow, [*[a for a, _ in groups[0].key], "seed", "event_frames", "return_before", "return_after"])
    )
    return [
        Heading(2, "Training return around rank events"),
        Paragraph(
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
            + ". Data in event_window.csv."
        ),
        Table(header, table),
    ]
