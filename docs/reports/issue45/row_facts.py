"""The facts a Table 1 row's verdict paragraph quotes, read from its committed report (no estimate computed here):
per method the mean ± std, IQM, seeds' scores, seeds above the plateau, the training wall time per run, and per
pair P(AdaRL > X) [95% CI], the exact Mann-Whitney p and the verdict, as make_report.sh wrote them; so a paragraph is
written from the same files tests/test_committed_reports.py re-derives, not typed from a screen. For the row's
described, no-rule reading (post hoc): each method's mean nominal curve at every 60k frames (learning_curves.csv) and
each low-rank layer's final ranks over the seeds (rank_settling.csv).

    .venv/bin/python docs/reports/issue45/row_facts.py docs/reports/table1-ant
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _wall_times(report: Path, algorithm: str) -> list[float]:
    """Each committed run's training wall time (summary.json), in seconds."""
    out = []
    for summary in sorted(report.glob(f"runs/*algorithm={algorithm}__seed=*/summary.json")):
        out.append(float(json.loads(summary.read_text())["wall_time_s"]))
    return out


#: the frames at which a method's mean curve is quoted (every 60k of the 300k budget: on the 20k evaluation grid)
CURVE_FRAMES = (60_000, 120_000, 180_000, 240_000, 300_000)


def _curve(report: Path, env: str, algorithm: str) -> str:
    """The method's mean nominal return at CURVE_FRAMES (the evaluation nearest each, from learning_curves.csv)."""
    points = [
        (int(r["frames"]), float(r["mean"]))
        for r in _rows(report / "learning_curves.csv")
        if r["group"] == f"env={env}, algorithm={algorithm}"
    ]
    if not points:
        return "no curve"
    quoted = []
    for f in CURVE_FRAMES:
        frames, mean = min(points, key=lambda p: abs(p[0] - f))
        quoted.append(f"{frames // 1000}k {mean:.0f}")
    return ", ".join(quoted)


def _ranks(report: Path, algorithm: str) -> list[str]:
    """Per low-rank layer: its initial rank and its final ranks over the seeds (range, median; rank_settling.csv)."""
    path = report / "rank_settling.csv"
    if not path.exists():
        return []
    layers: dict[str, list[dict[str, str]]] = {}
    for r in _rows(path):
        if r["algorithm"] == algorithm:
            layers.setdefault(r["layer"], []).append(r)
    out = []
    for layer, rows in layers.items():
        final = sorted(int(r["final_rank"]) for r in rows)
        mid = len(final) // 2
        median = final[mid] if len(final) % 2 else (final[mid - 1] + final[mid]) / 2
        initial = sorted({r["initial_rank"] for r in rows})
        out.append(
            f"{layer}: {'/'.join(initial)} -> {final[0]}-{final[-1]} (median {median:g}; {len(final)} seeds,"
            f" events {'/'.join(sorted({r['events'] for r in rows}))})"
        )
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="a row's report folder, e.g. docs/reports/table1-ant")
    args = parser.parse_args(argv)
    stats = {r["algorithm"]: r for r in _rows(args.report / "statistics.csv")}
    (env,) = {r["env"] for r in stats.values()}  # a row's report: one env
    table = {r["algorithm"]: r for r in _rows(args.report / "table.csv")}
    paper = {r["algorithm"]: r for r in _rows(args.report / "paper_table.csv") if r["env"] == env}
    for algorithm, s in stats.items():
        scores = ", ".join(f"{float(x):.0f}" for x in json.loads(table[algorithm]["scores"]))
        walls = _wall_times(args.report, algorithm)
        wall = f"{min(walls):.0f}-{max(walls):.0f} s a run" if walls else "no wall time"
        p = paper.get(algorithm, {})
        print(
            f"{env} {algorithm}: n={s['n_seeds']} {float(s['mean']):.0f} ± {float(s['std']):.0f}"
            f" (IQM {float(s['iqm']):.0f};"
            f" seeds {scores}); above the {float(s['plateau']):.0f} plateau: {s['above_plateau']} of {s['n_seeds']};"
            f" {wall}; paper {p.get('paper_mean') or '-'}; protocol bold: {p.get('protocol') or '-'}"
        )
        print(f"  mean curve: {_curve(args.report, env, algorithm)}")
        for line in _ranks(args.report, algorithm):
            print(f"  rank {line}")
        if not math.isnan(float(s["poi_ref"])):
            mw = float(p["mannwhitney_p"]) if p.get("mannwhitney_p") else float("nan")
            print(
                f"  P(adarl > {algorithm}) = {float(s['poi_ref']):.2f} [{float(s['poi_lo']):.2f},"
                f" {float(s['poi_hi']):.2f}], exact p = {mw:.3f}: {s['verdict'] or 'waits'}"
            )


if __name__ == "__main__":
    main()
