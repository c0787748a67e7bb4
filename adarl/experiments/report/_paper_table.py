"""The report's sections for ``report.paper_table``: the paper's table as it prints it, its mean ± std beside ours
in every cell with both bold rules, P(reference > each method) per row, and rliable's aggregate across its rows on
normalised scores (mean, IQM, optimality gap, performance profile). Private module of
:mod:`adarl.experiments.report`; the spec's part is :mod:`adarl.experiments._paper_spec`.

The two bold rules of a row, both over the paper's own methods only (not its ``extra_columns``):

* the paper's: the best mean of the row (applied to the paper's numbers and, separately, to ours among the methods
  with runs);
* the protocol's: a method is "not beaten" when no other method of the row with runs beats it by the decision rule
  (:func:`~adarl.experiments.report._sections.verdict`: P's 95% interval excludes 0.5, with ``verdict_seeds`` reached);
  while one of its comparisons waits for seeds it is neither.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import ValidationError
from scipy.stats import mannwhitneyu

from adarl.errors import RecipeError
from adarl.experiments._paper_spec import PaperTable
from adarl.experiments.report._blocks import Block, Bold, Heading, Image, Paragraph, Table, csv_text
from adarl.experiments.report._figures import figure_formats, plot_normalised_aggregate
from adarl.experiments.report._runs import Aggregate, Group
from adarl.experiments.report._sections import _planned_seeds, verdict
from adarl.experiments.report.stats import interval_estimate, performance_profile, poi_estimate

__all__ = ["paper_table_of", "paper_table_blocks", "protocol_status"]

MARK = "†"  # not beaten by the protocol's rule


def paper_table_of(report: dict) -> PaperTable | None:
    """``report["paper_table"]`` (a mapping from a spec or experiment.json, or the model) checked, or None."""
    raw = report.get("paper_table")
    if raw is None or isinstance(raw, PaperTable):
        return raw
    try:
        return PaperTable.model_validate(raw)
    except ValidationError as err:
        raise RecipeError(f"report.paper_table is invalid: {err}") from None


def _mean_std(g: Group | None) -> str:
    return "not run" if g is None else f"{g.mean:.1f} ± {g.std:.1f} (n={len(g.scores)})"


def _best(means: dict[str, float]) -> set[str]:
    """The methods with the best mean (all of them on a tie); none of an empty row."""
    top = max(means.values(), default=None)
    return {m for m, v in means.items() if v == top}


def protocol_status(groups: dict[str, Group], need) -> dict[str, str]:
    """Per method with runs: "not beaten", "beaten by a, b" or "waits" (a comparison of it has fewer seeds than
    ``need`` plans and none beats it yet), by the decision rule on P(a > b) for every two methods; {} with fewer than
    two methods run (nothing to compare)."""
    run = [m for m, g in groups.items() if g is not None]
    if len(run) < 2:
        return {}
    beaten: dict[str, list[str]] = {m: [] for m in run}
    waits: set[str] = set()
    for i, a in enumerate(run):
        for b in run[i + 1 :]:
            ga, gb = groups[a], groups[b]
            said = verdict(poi_estimate(ga.scores, gb.scores), a, b, (len(ga.scores), len(gb.scores)), need)
            if said == f"{a} beats {b}":
                beaten[b].append(a)
            elif said == f"{b} beats {a}":
                beaten[a].append(b)
            elif said != "no difference shown":  # waits for seeds (or no interval)
                waits |= {a, b}
    return {
        m: f"beaten by {', '.join(beaten[m])}" if beaten[m] else ("waits" if m in waits else "not beaten") for m in run
    }


def paper_table_blocks(agg: Aggregate, out: Path) -> list[Block]:
    """The paper's table beside ours and the aggregate across its rows; writes paper_table.csv (and, with
    ``normalise``, normalised_scores.csv, normalised_aggregate.csv and the figure). [] without report.paper_table."""
    table = paper_table_of(agg.report)
    if table is None:
        return []
    col = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    row_axis = table.row_axis(agg.axes, col)
    heading = Heading(2, f"{table.title} as the paper prints it")
    if col is None or row_axis is None or set(agg.axes) != {col, row_axis}:
        return [
            heading,
            Paragraph(
                f"report.paper_table needs runs whose axes are its rows ({row_axis or table.rows}) and the column axis "
                f"({col}); these runs' axes: {', '.join(agg.axes) or 'none'}."
            ),
        ]
    by = {(dict(g.key)[row_axis], dict(g.key)[col]): g for g in agg.groups if g.scores}
    need = agg.report.get("verdict_seeds")
    ref = agg.report.get("reference")
    ref = ref if ref in table.columns else table.columns[0]
    shown = [*table.columns, *table.extra_columns]
    header = [row_axis] + [f"{table.label(m)} ({m})" if table.label(m) != m else m for m in table.columns]
    header += [f"{table.label(m)} (not in the paper's {table.title})" for m in table.extra_columns]
    header.append(f"not beaten by the protocol's rule ({MARK})")
    others = [m for m in shown if m != ref]
    p_header = [row_axis] + [f"P({ref} > {m}) [95% CI]: verdict" for m in others]
    rows, p_rows, crow = [], [], []
    for row, cells in table.values.items():
        ours = {m: by.get((row, m)) for m in shown}
        paper_best = _best({m: cells[m][0] for m in table.columns})
        our_best = _best({m: ours[m].mean for m in table.columns if ours[m] is not None})
        status = protocol_status({m: ours[m] for m in table.columns}, need)
        line = [row]
        for m in table.columns:
            mine = _mean_std(ours[m])
            theirs = f"{cells[m][0]:.2f} ± {cells[m][1]:.2f}"
            line.append(
                [
                    "ours: ",
                    Bold(mine) if m in our_best else mine,
                    f" {MARK}" if status.get(m) == "not beaten" else "",
                    " · paper: ",
                    Bold(theirs) if m in paper_best else theirs,
                ]
            )
        line += [f"ours: {_mean_std(ours[m])}" for m in table.extra_columns]
        run = [m for m in table.columns if ours[m] is not None]
        if len(run) < 2:
            line.append("one method run" if run else "none run")
        else:
            free = [m for m in run if status[m] == "not beaten"]
            waiting = [m for m in run if status[m] == "waits"]
            said = [", ".join(free)] if free else []
            said += [f"waiting for seeds: {', '.join(waiting)}"] if waiting else []
            line.append("; ".join(said) or "–")
        rows.append(line)
        p_line = [row]
        for m in shown:
            g, r = ours[m], ours[ref]
            p, said, mw = (math.nan,) * 3, "", math.nan
            if m != ref:
                if g is not None and r is not None:
                    p = poi_estimate(r.scores, g.scores)
                    said = verdict(p, ref, m, (len(r.scores), len(g.scores)), need)
                    mw = float(mannwhitneyu(r.scores, g.scores, alternative="two-sided", method="exact").pvalue)
                    p_line.append(f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}] (p = {mw:.3f}): {said}")
                else:
                    p_line.append("not run: " + " and ".join(x for x in (ref, m) if ours[x] is None))
            crow.append(
                [
                    row,
                    m,
                    table.label(m),
                    m in table.columns,
                    *(cells[m] if m in table.columns else ("", "")),
                    m in paper_best,
                    0 if g is None else len(g.scores),
                    "" if g is None else g.mean,
                    "" if g is None else g.std,
                    m in our_best,
                    status.get(m, ""),
                    *p,
                    mw,
                    said,
                ]
            )
        p_rows.append(p_line)
    (out / "paper_table.csv").write_text(
        csv_text(
            crow,
            [
                row_axis,
                col,
                "label",
                "in_paper_table",
                "paper_mean",
                "paper_std",
                "paper_bold",
                "n_seeds",
                "mean",
                "std",
                "bold_by_papers_rule",
                "protocol",
                "poi_ref",
                "poi_lo",
                "poi_hi",
                "mannwhitney_p",
                "verdict",
            ],
        )
    )
    waits = f", once both sides have {_planned_seeds(need)}" if need else ""
    blocks: list[Block] = [
        heading,
        Paragraph(
            (f"{table.source} " if table.source else "")
            + f"Each cell: ours (mean ± sample std of the runs' scores across seeds, n seeds; 'not run' without "
            f"runs) · the paper's mean ± std. Bold by the paper's rule, applied to its numbers and to ours apart: "
            f"the best mean of the row among the paper's {len(table.columns)} methods (ours: among those with runs). "
            f"{MARK}: by the protocol's rule, no other of the paper's methods with runs in the row beats it "
            f"(P(a > b)'s 95% stratified-bootstrap interval excludes 0.5{waits}); a method one of whose comparisons "
            "waits for seeds is not marked. Our budget and physics are the experiment's (see above), not "
            "necessarily the paper's. Data in paper_table.csv."
        ),
        Table(header, rows),
        Paragraph(
            f"P({ref} > each method) per row: the probability that a run of {ref} scores above a run of the method "
            "(ties count half) with its 95% stratified-bootstrap interval, the exact two-sided Mann-Whitney p of the "
            "same two sets of scores (for a reader who counts the pairs tested; the rule does not use it), and the "
            "decision rule's verdict (one side beats the other when the interval excludes 0.5, else 'no difference "
            f"shown'{waits})."
        ),
        Table(p_header, p_rows),
    ]
    if table.normalise is not None:
        blocks += _aggregate_blocks(table, by, row_axis, out, figure_formats(agg))
    return blocks


def _ci(est: tuple[float, float, float]) -> str:
    pt, lo, hi = est
    if math.isnan(pt):
        return "–"
    return f"{pt:.2f}" if math.isnan(lo) else f"{pt:.2f} [{lo:.2f}, {hi:.2f}]"


def _aggregate_blocks(table: PaperTable, by: dict, row_axis: str, out: Path, formats: tuple[str, ...]) -> list[Block]:
    """rliable's aggregate across the table's rows on normalised scores; writes its CSVs and figure (in
    ``formats``)."""
    norm = table.normalise
    heading = Heading(2, f"{table.title} across {', '.join(table.values)}: normalised aggregate")
    methods = [m for m in (*table.columns, *table.extra_columns) if any((r, m) in by for r in table.values)]
    if not methods:
        return [heading, Paragraph(f"No runs in the rows of {table.title} ({', '.join(table.values)}) yet.")]
    ref = "the paper's best" if norm.reference == "best" else f"the paper's {table.label(norm.reference)}"
    per_run, rows, crow, estimates, tasks = [], [], [], {}, {}
    for m in methods:
        envs = [r for r in table.values if (r, m) in by]
        tasks[m] = []
        for r in envs:
            g = by[(r, m)]
            xs = [table.normalised(r, s) for s in g.scores]
            tasks[m].append(xs)
            per_run += [[r, m, run.seed, s, x] for run, s, x in zip(g.scored, g.scores, xs)]
        est = {
            "mean": interval_estimate(tasks[m], "mean"),
            "iqm": interval_estimate(tasks[m], "iqm"),
            "optimality_gap": interval_estimate(tasks[m], "optimality_gap", gamma=1.0),
        }
        paper = (
            float(np.mean([table.normalised(r, table.values[r][m][0]) for r in envs]))
            if m in table.columns
            else math.nan
        )
        name = table.label(m) if m in table.columns else f"{table.label(m)} (not in {table.title})"
        estimates[name] = est
        n = sum(len(t) for t in tasks[m])
        rows.append(
            [
                name,
                f"{len(envs)}/{len(table.values)}: {', '.join(envs)}",
                str(n),
                _ci(est["mean"]),
                _ci(est["iqm"]),
                _ci(est["optimality_gap"]),
                "–" if math.isnan(paper) else f"{paper:.2f}",
            ]
        )
        crow.append([m, ";".join(envs), n, *est["mean"], *est["iqm"], *est["optimality_gap"], paper])
    everything = [x for m in methods for t in tasks[m] for x in t]
    taus = np.linspace(min(0.0, min(everything)), max(1.25, max(everything)), 81)
    profiles = {name: performance_profile(tasks[m], taus) for name, m in zip(estimates, methods)}
    png = plot_normalised_aggregate(estimates, taus, profiles, out, formats=formats)
    (out / "normalised_scores.csv").write_text(csv_text(per_run, [row_axis, "method", "seed", "score", "normalised"]))
    (out / "normalised_aggregate.csv").write_text(
        csv_text(
            crow,
            [
                "method",
                row_axis,
                "runs",
                "mean",
                "mean_lo",
                "mean_hi",
                "iqm",
                "iqm_lo",
                "iqm_hi",
                "optimality_gap",
                "optimality_gap_lo",
                "optimality_gap_hi",
                "paper_mean_normalised",
            ],
        )
    )
    randoms = ", ".join(f"{r} {v:g}" for r, v in norm.random.items())
    header = [
        "method",
        f"{row_axis} with runs",
        "runs",
        "mean [95% CI]",
        "IQM [95% CI]",
        "optimality gap [95% CI]",
        "paper: mean of its normalised means",
    ]
    return [
        heading,
        Paragraph(
            f"Normalised score of a run: (score - random) / (reference - random) in its {row_axis}, with random the "
            f"return of uniform random actions on the nominal dynamics ({randoms}"
            + (f"; {norm.random_from}" if norm.random_from else "")
            + f") and reference {ref} mean of that {row_axis}: 0 = random actions, 1 = {ref}. Per method, pooled over "
            f"its runs in every {row_axis} it has runs in (the second column; compare methods over the same "
            f"{row_axis} values): the mean and the IQM of the normalised scores, and the optimality gap at 1 "
            f"(1 - mean(min(x, 1)): how far the runs fall short of {ref} on average; 0 = every run at or above it), "
            f"each with a 95% stratified-bootstrap interval (2000 resamples within each {row_axis}, fixed seed; "
            "rliable's estimators, adarl.experiments.report.stats). Paper: the mean over the same rows of the paper's "
            "own means, normalised alike (its runs are not published: no IQM, gap or interval). The performance "
            "profile is the share of runs whose normalised score exceeds tau, with its 95% band. Data in "
            "normalised_aggregate.csv, normalised_scores.csv and normalised_profile.csv."
        ),
        Table(header, rows),
        *([Image(png.name, "normalised aggregate and performance profile")] if png is not None else []),
    ]
