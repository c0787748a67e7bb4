"""Reports across run folders: tables, statistics, curves, ranks, sweeps and the paper's Table 1.

The hub of the report wing; the work is done in private modules, one job each (as TorchRL splits its transforms):
``_runs`` (run folders to records and groups), ``_sections`` (tables, statistics and the decision rule),
``_figures`` (plots), ``_blocks`` (Markdown, HTML and CSV), ``_paper_table`` (Table 1 as the paper prints it; its
spec section, :mod:`adarl.experiments._paper_spec`, sits beside the experiment spec), ``_aggregate`` (the report
itself: :func:`write_aggregate_report`). The estimators (IQM, stratified bootstrap, probability of improvement,
optimality gap, performance profile) are :mod:`adarl.experiments.report.stats`.
"""

from __future__ import annotations

from adarl.experiments.report._aggregate import write_aggregate_report
from adarl.experiments.report._runs import (
    Aggregate,
    Group,
    RunRecord,
    aggregate_runs,
    axes_from_run_id,
    collect_runs,
    event_dips,
    is_single_run,
    rank_settling,
)
from adarl.experiments.report._sections import verdict

__all__ = [
    "RunRecord",
    "Group",
    "Aggregate",
    "collect_runs",
    "aggregate_runs",
    "axes_from_run_id",
    "write_aggregate_report",
    "is_single_run",
    "event_dips",
    "rank_settling",
    "verdict",
]
