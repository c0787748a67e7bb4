"""Aggregate many run folders (seeds x settings) into one report: tables, statistics, curves, ranks, sweeps.

``adarl report DIR...`` with several folders, or an experiment folder, lands here. Every number is read from the
run folders (``eval.csv``, ``ranks.json``, ``metrics/``, ``sweeps/``); nothing is typed in. Runs are grouped by
their experiment axes (from ``experiment.json``) or, for loose run folders, by recipe name; seeds are the
replicates. A run's score is the mean of its last ``report.score_last`` nominal-dynamics evaluations (1 by
default: the last one; issue 34's protocol uses 3); a group's score is the mean ± sample std of its seeds' scores
(the paper's Table 1 convention), with the number of seeds shown.

:mod:`adarl.experiments.report` is the hub; the work is done in private modules, one job each: this one writes the
report; :mod:`~adarl.experiments.report._runs` (run folders to records and groups),
:mod:`~adarl.experiments.report._sections` (tables, statistics and the decision rule),
:mod:`~adarl.experiments.report._figures` (plots), :mod:`~adarl.experiments.report._blocks` (Markdown, HTML and CSV).

Outputs in the report folder: ``report.md``, ``report.html``, ``table.csv``, ``runs.csv``, ``statistics.csv``, and
per figure a PNG, a PDF and an SVG (``report.formats``; the report links the PNG) with the CSV it was drawn from:
``learning_curves``, ``learning_curves_by_seed``, ``ranks``, ``return_vs_<axis>`` (Fig. 1), ``sweep_<name>``
(Fig. 8); with ``report.paper_table``
(:mod:`~adarl.experiments.report._paper_table`), ``paper_table.csv`` and the normalised aggregate (``normalised_*``).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path

from adarl.errors import RecipeError
from adarl.experiments.report._blocks import (
    Code,
    Heading,
    Image,
    Paragraph,
    Table,
    csv_text,
    render_html,
    render_markdown,
)
from adarl.experiments.report._figures import (
    CI_BAND,
    CI_BAND_HOW,
    STD_BAND,
    STD_BARS,
    figure_formats,
    plot_learning_curves,
    plot_rank_trajectories,
    plot_return_vs,
    plot_rliable,
    plot_setting_curves,
    plot_sweeps,
    rank_x_label,
)
from adarl.experiments.report._paper_table import paper_table_blocks
from adarl.experiments.report._runs import (
    _num_key,
    aggregate_runs,
)
from adarl.experiments.report._sections import _rank_settling_blocks, _statistics_blocks, _table
from adarl.runtime.run_folder.results import download_results, exists, is_url, join, upload_tree

__all__ = ["write_aggregate_report"]


def write_aggregate_report(
    dirs: list[str | os.PathLike],
    output: str | os.PathLike | None = None,
    *,
    command: str | None = None,
    report: dict | None = None,
    pair_values: dict[str, set[str]] | None = None,
) -> Path | str:
    """Aggregate the runs in ``dirs`` and write the report folder; returns the path of its ``report.md``.

    ``dirs`` and ``output`` may be fsspec URLs (:mod:`adarl.runtime.run_folder.results`): the runs' files (not their
    checkpoints)
    are copied to a temporary folder, the report is made there and uploaded (default output: ``<URL>/report`` for one
    experiment at a URL); ``runs.csv`` names the runs by their URL, and the URL of ``report.md`` is returned.
    ``report``: keys of an experiment spec's ``report`` section over the experiments' own (``adarl report --set``;
    validate them with :func:`~adarl.experiments.spec.report_options`). ``pair_values``: check ``report.pairs``
    against the column axis's values of the runs found plus ``pair_values[axis]`` (a spec's own ``{axis: values}``,
    which may have no runs yet): a value in neither is refused before anything is written (a typo in ``adarl report
    --set pairs=...``); a per-arm ``report.verdict_seeds`` is checked against the same values (and must name every
    arm of the runs)."""
    if any(is_url(d) for d in dirs) or is_url(output):
        return _write_report_via_copy(dirs, output, command=command, report=report, pair_values=pair_values)
    agg = aggregate_runs(dirs, report)
    if pair_values is not None:
        _check_pair_values(agg, pair_values)
    _check_verdict_seeds(agg, pair_values)
    formats = figure_formats(agg)  # a bad report.formats is refused before anything is written
    if output is None:
        only = Path(dirs[0]) if len(dirs) == 1 else None
        output = only / "report" if only is not None and (only / "experiment.json").is_file() else Path("report")
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    n_runs = sum(len(g.runs) for g in agg.groups)
    last = int(agg.report.get("score_last") or 1)
    rule = (
        "its last evaluation on the nominal dynamics (mean over its evaluation episodes)"
        if last == 1
        else f"the mean of its last {last} evaluations on the nominal dynamics (each the mean over its episodes)"
    )
    exps = agg.info["experiments"]
    names = list(dict.fromkeys(e["name"] for e in exps))  # a spec's budgets run into one folder: named once
    title = "Experiment report: " + ", ".join(names) if exps else "Aggregate report"
    blocks: list = [Heading(1, title)]
    for e in exps:
        if e.get("description"):
            blocks.append(Paragraph(f"{e['description']} (budget: {e.get('budget') or 'default'})."))
    blocks.append(
        Paragraph(
            f"{n_runs} runs in {len(agg.groups)} settings; seeds are replicates. Every number is read "
            f"from the run folders listed in runs.csv. Score of a run: {rule}; table cells: mean ± sample std of "
            "that score across seeds, n = number of seeds; best mean of each row in bold."
        )
    )
    commands = [command] if command else [e["command"] for e in exps if e.get("command")]
    if commands:
        blocks += [Paragraph("Produced by:"), Code("\n".join(commands))]
    if report:
        given = ", ".join(f"{k}={_option_text(k, v)}" for k, v in report.items())
        blocks.append(
            Paragraph(f"Report options given to `adarl report` (--spec, --set; over the experiments' own): {given}.")
        )
    if agg.info["unfinished"]:
        blocks.append(Paragraph("Not finished (left out): " + "; ".join(agg.info["unfinished"])))
    if agg.info["missing"]:
        blocks.append(Paragraph("Not run (recipe missing): " + "; ".join(agg.info["missing"])))
    header, rows, bold = _table(agg)
    blocks += [Heading(2, "Score on nominal dynamics"), Table(header, rows, bold)]
    table_rows = [
        [
            *[v for _, v in g.key],
            len(g.scores),
            g.mean,
            g.std,
            min(g.scores, default=math.nan),
            max(g.scores, default=math.nan),
            json.dumps(g.seeds),
            json.dumps(g.scores),
        ]
        for g in agg.groups
    ]
    (out / "table.csv").write_text(
        csv_text(table_rows, [*agg.axes, "n_seeds", "mean", "std", "min", "max", "seeds", "scores"])
    )
    (out / "runs.csv").write_text(
        csv_text(
            [
                [
                    str(r.path),
                    *[r.axes.get(a, "-") for a in agg.axes],
                    r.seed,
                    r.env_id,
                    r.final,
                    r.evals[-1][0] if r.evals else None,
                    r.updates,
                    r.score(last),
                    last,
                    r.best,
                ]
                for g in agg.groups
                for r in g.runs
            ],
            [
                "path",
                *agg.axes,
                "seed",
                "env_id",
                "final_return",
                "frames",
                "updates",
                "score",
                "score_last",
                "best_eval",
            ],
        )
    )

    blocks += _statistics_blocks(agg, out)
    blocks += paper_table_blocks(agg, out)

    col_axis = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    p = plot_rliable(agg, out, agg.report.get("reference"), col_axis)
    if p is not None:
        blocks += [
            Heading(2, "Interval estimates, performance profile, probability of improvement"),
            Paragraph(
                "rliable's figures (Agarwal et al. 2021) from the same scores: mean and IQM with 95% stratified-"
                "bootstrap intervals, the share of runs scoring above each threshold, and the probability that the "
                "reference improves on each setting (dashed line: 0.5, no difference). Data in rliable.csv."
                + _formats_note(formats)
            ),
            Image(p.name, "interval estimates, performance profile, probability of improvement"),
        ]
    x_axis = agg.report.get("x_axis") or ("rank" if "rank" in agg.axes else None)
    if x_axis:
        p = plot_return_vs(agg, x_axis, out)
        if p is not None:
            blocks += [
                Heading(2, f"Score vs {x_axis}"),
                Paragraph(
                    f"Final return, mean over seeds ({STD_BARS}); data in {p.with_suffix('.csv').name}."
                    + _formats_note(formats)
                ),
                Image(p.name, f"score vs {x_axis}"),
            ]
    p, _ = plot_learning_curves(agg, out)
    if p is not None:
        blocks += [
            Heading(2, "Learning curves"),
            Paragraph(
                f"Nominal-dynamics evaluation against environment frames: mean across seeds; {CI_BAND} "
                f"({CI_BAND_HOW}). Each evaluation is placed at the end of its eval.interval bin so that the seeds "
                "line up; dotted lines mark the first seed's rank events (and the restarts of a control that restarts "
                "without truncating). Data in learning_curves.csv (with the std over seeds as well)."
                + _formats_note(formats)
            ),
            Image(p.name, "learning curves"),
        ]
    p = plot_setting_curves(agg, out)
    if p is not None:
        blocks += [
            Heading(2, "Every seed's learning curve"),
            Paragraph(
                "One panel per setting: each seed's nominal evaluations (thin; a seed has the same colour in every "
                "panel, named in the legend), their mean (black), each seed's rank events or restarts (dotted, the "
                "seed's colour)"
                + (", the plateau threshold (dashed)" if agg.report.get("plateau") is not None else "")
                + ". Data in learning_curves_by_seed.csv."
                + _formats_note(formats)
            ),
            Image(p.name, "learning curves by seed"),
        ]
    p = plot_rank_trajectories(agg, out)
    if p is not None:
        blocks += [
            Heading(2, "Rank trajectories"),
            Paragraph(
                f"Rank of each factorised layer over {rank_x_label(agg)}, every seed; the red dashed line is "
                "the intrinsic rank (2*d_a+1, Tiwari et al. 2025; or the spec's report.intrinsic_rank). Each layer "
                "has its own colour, line style and marker, named in the legend; the layers drawn first are wider, "
                "so that two layers at the same rank both show. Data in ranks.csv." + _formats_note(formats)
            ),
            Image(p.name, "ranks"),
        ]
    blocks += _rank_settling_blocks(agg, out)
    for name, path, summary in plot_sweeps(agg, out):
        blocks += [
            Heading(2, f"Robustness sweep: {name}"),
            Paragraph(
                f"Per grid point: mean across seeds of the per-point mean return ({STD_BAND}); dotted: the worst "
                "single episode at each point over all seeds; red stars: each setting's worst case. Data in "
                + path.with_suffix(".csv").name
                + "."
                + _formats_note(formats)
            ),
            Table(
                ["group", "seeds", "average over grid", "worst mean", "worst case"],
                [[s[0], s[1], f"{s[2]:.1f}", f"{s[3]:.1f}", f"{s[4]:.1f}"] for s in summary],
            ),
            Image(path.name, f"sweep {name}"),
        ]
    (out / "report.md").write_text(render_markdown(blocks))
    (out / "report.html").write_text(render_html(blocks))
    return out / "report.md"


def _formats_note(formats: tuple[str, ...]) -> str:
    """The sentence that says where the figure's vector copies are (none when the report writes PNG only)."""
    others = [f.upper() for f in formats if f != "png"]
    return f" The figure is also written as {' and '.join(others)} beside the PNG (same name)." if others else ""


def _option_text(key: str, value) -> str:
    """A report option as the report names it; ``paper_table`` by its title and size (its values: its section)."""
    if key == "paper_table" and isinstance(value, dict):
        rows = value.get("values") or {}
        return f"{json.dumps(value.get('title'))} ({len(rows)} rows x {len(value.get('columns') or [])} columns)"
    return json.dumps(value)


def _check_pair_values(agg, allowed: dict[str, set[str]]) -> None:
    col = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    pairs = agg.report.get("pairs") or []
    if col is None or not pairs:
        return
    extra = {str(v) for v in allowed.get(col, ())}
    known = {dict(g.key)[col] for g in agg.groups if col in dict(g.key)} | extra
    unknown = sorted({str(v) for pair in pairs for v in pair} - known)
    if unknown:
        raise RecipeError(
            f"report.pairs name {unknown}, not values of the column axis {col!r} in these runs"
            f"{' or the spec' if extra else ''}: {sorted(known, key=_num_key)}"
        )


def _check_verdict_seeds(agg, allowed: dict[str, set[str]] | None) -> None:
    """A per-arm ``report.verdict_seeds`` names every arm of the runs (an arm left out would get a verdict with no
    planned count); given on the command line (``allowed`` not None: the spec's ``{axis: values}``, or ``{}``), only
    values of the column axis, of the runs or of the spec. An experiment's own mapping was checked against its spec's
    arms, which a budget may run only some of."""
    need = agg.report.get("verdict_seeds")
    if not isinstance(need, dict):
        return
    col = agg.report.get("columns") or ("algorithm" if "algorithm" in agg.axes else None)
    if col is None:
        raise RecipeError(f"report.verdict_seeds per arm needs a column axis (report.columns); none in {agg.axes}")
    found = {dict(g.key)[col] for g in agg.groups if col in dict(g.key)}
    known = found | {str(v) for v in (allowed or {}).get(col, ())} | (set(need) if allowed is None else set())
    unknown = sorted(set(need) - known, key=_num_key)
    missing = sorted(found - set(need), key=_num_key)
    if unknown or missing:
        said = []
        if unknown:
            said.append(f"names {unknown}, not values of the column axis {col!r}")
        if missing:
            said.append(f"has no seed count for {missing}")
        raise RecipeError(
            f"report.verdict_seeds {' and '.join(said)}; the arms: {sorted(known, key=_num_key)} (give one count "
            "for all, or one for each)"
        )


def _write_report_via_copy(
    dirs: list, output, *, command: str | None, report: dict | None, pair_values: dict | None = None
) -> Path | str:
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
        md = write_aggregate_report(local_dirs, local_out, command=command, report=report, pair_values=pair_values)
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
