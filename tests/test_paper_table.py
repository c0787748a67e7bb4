"""``report.paper_table`` (issue 45): the paper's table beside ours in every cell, both bold rules, P(reference > each
method) per row, and rliable's aggregate across the rows on normalised scores (mean, IQM, optimality gap,
performance profile), on synthetic run folders whose every number is computed by hand here; the spec's errors for a
bad table; and the two estimators it adds to adarl.experiments.report.stats."""

from __future__ import annotations

import csv
import re

import numpy as np
import pytest
from scipy.stats import mannwhitneyu
from test_evaluation_experiments import _fake_run, _spec

from adarl.errors import RecipeError
from adarl.experiments.report.stats import interval_estimate, optimality_gap, performance_profile, poi_estimate

# ------------------------------------------------------------------------------------------- estimators


def test_optimality_gap_is_the_mean_shortfall_below_gamma():
    assert optimality_gap([0.5, 1.5, 0.8]) == pytest.approx(1 - (0.5 + 1.0 + 0.8) / 3)  # 1.5 counts as 1
    assert optimality_gap([0.5, 1.5, 0.8], gamma=2.0) == pytest.approx(2 - (0.5 + 1.5 + 0.8) / 3)
    assert optimality_gap([1.0, 3.0]) == 0.0 and np.isnan(optimality_gap([]))
    # pooled over tasks; the interval is the stratified bootstrap's, resample by resample
    tasks = [np.array([0.2, 0.9, 1.4]), np.array([0.5, 1.1])]
    pt, lo, hi = interval_estimate(tasks, "optimality_gap", reps=300, seed=4)
    assert pt == pytest.approx(1 - (0.2 + 0.9 + 1.0 + 0.5 + 1.0) / 5)
    draws = np.random.default_rng(4)
    boot = [
        1 - np.mean(np.minimum(np.concatenate([t[draws.integers(0, t.size, t.size)] for t in tasks]), 1.0))
        for _ in range(300)
    ]
    assert (lo, hi) == (float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975)))


def test_performance_profile_is_the_share_above_each_tau_with_a_stratified_band():
    tasks = [np.array([0.5, 1.5]), np.array([1.0, 2.0, 3.0])]
    share, lo, hi = performance_profile(tasks, [0.0, 1.0, 2.0], reps=300, seed=2)
    assert share.tolist() == [1.0, 0.6, 0.2]  # pooled: >0 all 5; >1: 1.5, 2, 3; >2: 3 (1.0 and 2.0 not above)
    draws = np.random.default_rng(2)
    boot = []
    for _ in range(300):
        pooled = np.concatenate([t[draws.integers(0, t.size, t.size)] for t in tasks])
        boot.append([np.mean(pooled > tau) for tau in (0.0, 1.0, 2.0)])
    assert lo.tolist() == np.quantile(boot, 0.025, axis=0).tolist()
    assert hi.tolist() == np.quantile(boot, 0.975, axis=0).tolist()
    assert np.all(lo <= share) and np.all(share <= hi)
    one, lo1, _ = performance_profile([0.3], [0.0, 0.5])
    assert one.tolist() == [1.0, 0.0] and np.isnan(lo1).all()  # one run: no band
    with pytest.raises(ValueError, match="optimality_gap"):
        interval_estimate([1.0, 2.0], "median")


# ------------------------------------------------------------------------------------------- the spec

TABLE = {
    "title": "Table 9",
    "source": "A synthetic table.",
    "columns": ["a", "b", "c"],
    "labels": {"a": "Alg A", "x": "Extra X"},
    "extra_columns": ["x"],
    "values": {
        "hopper": {"a": [100, 10], "b": [80, 5], "c": [120, 1]},  # the paper's bold: c
        "walker2d": {"a": [200, 20], "b": [150, 10], "c": [50, 5]},  # the paper's bold: a
    },
    "normalise": {"random": {"hopper": 0, "walker2d": 100}, "reference": "a", "random_from": "made up"},
}
AXES = {"env": ["hopper", "walker2d", "ant"], "algo": ["a", "b", "c", "x"]}


def _with(**changes) -> dict:
    table = {**TABLE, **changes}
    return {k: v for k, v in table.items() if v is not None}


@pytest.mark.parametrize(
    ("table", "match"),
    [
        (_with(columns=["a", "b", "zz"]), r"paper_table: values.hopper names \['c'\], not one of the paper's columns"),
        (
            _with(columns=["a", "zz"], values={"hopper": {"a": [1, 1], "zz": [1, 1]}}, normalise=None),
            r"report.paper_table.columns name \['zz'\], not values of the column axis 'algo'",
        ),
        (
            _with(extra_columns=["sac"], labels={}),
            r"paper_table.extra_columns name \['sac'\], not values of the column axis 'algo'",
        ),
        (
            _with(values={"hoper": TABLE["values"]["hopper"]}, normalise=None),
            r"values name rows \['hoper'\].*did you mean 'hopper'",
        ),
        (_with(values={"hopper": {"a": [1], "b": [1, 1], "c": [1, 1]}}), r"values.hopper.a must be \[mean, std\]"),
        (_with(values={"hopper": {"a": [1, -2], "b": [1, 1], "c": [1, 1]}}), r"std >= 0\), got \[1, -2\]"),
        (_with(values={"hopper": {"a": "2109.8 ± 3", "b": [1, 1], "c": [1, 1]}}), r"must be \[mean, std\]"),
        (
            _with(values={"hopper": {"a": [1, 1], "b": [1, 1]}}),
            r"paper_table: values.hopper has no \[mean, std\] for \['c'\]",
        ),
        (_with(values={"hopper": {"a": [1, 1], "b": [1, 1], "c": [1, 1], "cc": [1, 1]}}), r"did you mean 'c'"),
        (_with(columns=["a", "a"]), r"paper_table: columns repeats a method"),
        (_with(labels={"q": "Q"}), r"paper_table: labels name \['q'\], not a column"),
        (_with(normalise={"random": {"hopper": 0}, "reference": "a"}), r"normalise.random must give each row"),
        (_with(normalise={**TABLE["normalise"], "reference": "x"}), r"normalise.reference 'x' must be one of"),
        (_with(normalise={**TABLE["normalise"], "random": {"hopper": 500, "walker2d": 0}}), r"not above its random"),
        (_with(colums=["a"]), r"paper_table.colums: Extra inputs are not permitted"),
        (_with(rows="seed"), r"paper_table.rows must be an axis other than the column axis 'algo'"),
    ],
)
def test_a_bad_paper_table_is_refused_naming_what_is_allowed(tmp_path, table, match):
    from adarl.experiments.spec import load_experiment

    with pytest.raises(RecipeError, match=match):
        load_experiment(_spec(tmp_path, axes=AXES, report={"columns": "algo", "paper_table": table}))


def test_a_good_paper_table_loads_and_set_checks_it_too(tmp_path):
    from adarl.experiments.spec import load_experiment, report_options

    spec = load_experiment(_spec(tmp_path, axes=AXES, report={"columns": "algo", "paper_table": TABLE}))
    table = spec.report.paper_table
    assert table.values["hopper"]["c"] == (120.0, 1.0) and table.label("b") == "b" and table.label("a") == "Alg A"
    assert table.normalised("walker2d", 250.0) == pytest.approx(1.5)  # (250 - 100) / (200 - 100)
    with pytest.raises(RecipeError, match=r"values.hopper.a must be \[mean, std\]"):
        report_options(["paper_table={columns: [a], values: {hopper: {a: [1]}}}"])
    given = report_options(["paper_table={columns: [a], values: {hopper: {a: [1, 2]}}}"])
    assert given["paper_table"]["values"] == {"hopper": {"a": (1.0, 2.0)}}  # a plain mapping, as the report reads
    shipped = load_experiment("table1").report.paper_table
    assert shipped.columns == ["adarl", "rnac_ds", "rnac_ipm", "parseval", "sparse"]
    assert shipped.values["humanoid"]["parseval"] == (458.35, 76.41) and shipped.normalised("ant", 3067.13) == 1.0


# ------------------------------------------------------------------------------------------- the report

SCORES = {  # (env, algo) -> each seed's score (its last evaluation)
    ("hopper", "a"): [110, 120, 130],
    ("hopper", "b"): [10, 20, 30],
    ("hopper", "x"): [90, 95],
    ("walker2d", "a"): [150, 250, 350],
    ("walker2d", "b"): [200, 210, 220],
}


def _runs(tmp_path):
    root = tmp_path / "runs"
    for (env, algo), scores in SCORES.items():
        for seed, s in enumerate(scores):
            _fake_run(root, f"env={env}__algorithm={algo}__seed={seed}", seed, 0, [(100, 0.0), (200, float(s))])
    return root


def _md_rows(md: str, first_header_cell: str) -> dict[str, list[str]]:
    """The rows of the first Markdown table after a header row starting with ``first_header_cell``."""
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header_cell} |"))
    out = {}
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split(" | ")]
        out[cells[0]] = cells[1:]
    return out


def _report(tmp_path, **extra):
    from adarl.experiments.report import write_aggregate_report

    report = {"columns": "algorithm", "reference": "a", "paper_table": {**TABLE, "rows": "env"}, **extra}
    out = tmp_path / "report"
    return write_aggregate_report([_runs(tmp_path)], out, report=report).read_text(), out


def test_the_papers_table_beside_ours_with_both_bold_rules_and_p_per_row(tmp_path):
    md, out = _report(tmp_path, verdict_seeds={"a": 3, "b": 3, "x": 2})
    assert "## Table 9 as the paper prints it" in md and "A synthetic table." in md
    assert 'paper_table="Table 9" (2 rows x 3 columns)' in md  # the options line names it, not its values
    rows = _md_rows(md, "env | Alg A (a)")
    # hopper: ours best by the paper's rule among those run = a (120); the paper's own bold = c (120.00);
    # P(a > b) = 1 [1, 1]: a beats b, so a alone is not beaten (†)
    assert rows["hopper"] == [
        "ours: **120.0 ± 10.0 (n=3)** † · paper: 100.00 ± 10.00",
        "ours: 20.0 ± 10.0 (n=3) · paper: 80.00 ± 5.00",
        "ours: not run · paper: **120.00 ± 1.00**",
        "ours: 92.5 ± 3.5 (n=2)",
        "a",
    ]
    # walker2d: P(a > b) = 6/9, its interval holds 0.5: neither beats the other, both marked
    assert rows["walker2d"] == [
        "ours: **250.0 ± 100.0 (n=3)** † · paper: **200.00 ± 20.00**",
        "ours: 210.0 ± 10.0 (n=3) † · paper: 150.00 ± 10.00",
        "ours: not run · paper: 50.00 ± 5.00",
        "ours: not run",
        "a, b",
    ]
    p = _md_rows(md, "env | P(a > b) [95% CI]: verdict")
    pw = poi_estimate(SCORES["walker2d", "a"], SCORES["walker2d", "b"])
    assert pw[0] == pytest.approx(6 / 9) and pw[1] < 0.5 < pw[2]
    # exact two-sided Mann-Whitney p: 3 vs 3 all above, 2 of the C(6, 3) = 20 orderings as extreme; 3 vs 2: 2 of 10
    assert p["hopper"] == [
        "1.00 [1.00, 1.00] (p = 0.100): a beats b",
        "not run: c",
        "1.00 [1.00, 1.00] (p = 0.200): a beats x",
    ]
    mw = mannwhitneyu(SCORES["walker2d", "a"], SCORES["walker2d", "b"], method="exact").pvalue
    assert p["walker2d"] == [
        f"0.67 [{pw[1]:.2f}, {pw[2]:.2f}] (p = {mw:.3f}): no difference shown",
        "not run: c",
        "not run: x",
    ]
    html = (out / "report.html").read_text()
    assert "ours: <b>120.0 ± 10.0 (n=3)</b> † · paper: 100.00 ± 10.00" in html
    cells = {(r["env"], r["algorithm"]): r for r in csv.DictReader((out / "paper_table.csv").open())}
    assert cells["hopper", "a"]["protocol"] == "not beaten" and cells["hopper", "b"]["protocol"] == "beaten by a"
    assert cells["hopper", "a"]["bold_by_papers_rule"] == "True" and cells["hopper", "a"]["paper_bold"] == "False"
    assert cells["hopper", "c"]["n_seeds"] == "0" and cells["hopper", "c"]["paper_bold"] == "True"
    assert cells["hopper", "x"]["in_paper_table"] == "False" and cells["hopper", "x"]["verdict"] == "a beats x"
    assert float(cells["walker2d", "b"]["poi_ref"]) == pytest.approx(6 / 9)
    assert float(cells["hopper", "b"]["mannwhitney_p"]) == pytest.approx(0.1)


def test_no_mark_and_no_verdict_before_the_planned_seeds(tmp_path):
    md, out = _report(tmp_path, verdict_seeds=4)
    rows = _md_rows(md, "env | Alg A (a)")
    assert rows["hopper"][0] == "ours: **120.0 ± 10.0 (n=3)** · paper: 100.00 ± 10.00"  # the paper's rule still bolds
    assert rows["hopper"][-1] == "waiting for seeds: a, b" and rows["walker2d"][-1] == "waiting for seeds: a, b"
    p = _md_rows(md, "env | P(a > b) [95% CI]: verdict")
    assert p["hopper"][0] == "1.00 [1.00, 1.00] (p = 0.100): waits for 4 seeds each (has 3 and 3)"
    cells = {(r["env"], r["algorithm"]): r for r in csv.DictReader((out / "paper_table.csv").open())}
    assert {cells[k]["protocol"] for k in cells if cells[k]["n_seeds"] not in ("0", "2")} == {"waits"}


def test_the_normalised_aggregate_across_rows_is_the_hand_computation(tmp_path):
    md, out = _report(tmp_path)
    assert "## Table 9 across hopper, walker2d: normalised aggregate" in md and "made up" in md
    agg = {r["method"]: r for r in csv.DictReader((out / "normalised_aggregate.csv").open())}
    # normalised: hopper s / 100 (random 0, the paper's a 100); walker2d (s - 100) / 100 (random 100, a 200)
    a = [1.1, 1.2, 1.3, 0.5, 1.5, 2.5]
    b = [0.1, 0.2, 0.3, 1.0, 1.1, 1.2]
    want = {
        "a": (np.mean(a), np.mean([1.1, 1.2, 1.3, 1.5]), 1 - np.mean(np.minimum(a, 1)), 1.0),  # IQM: drop 0.5 and 2.5
        "b": (np.mean(b), np.mean([0.2, 0.3, 1.0, 1.1]), 1 - 3.6 / 6, np.mean([0.8, 0.5])),  # paper: 80/100, 50/100
        "x": (0.925, 0.925, 0.075, None),
    }
    assert set(agg) == set(want)  # c has no runs
    for m, (mean, iq, gap, paper) in want.items():
        r = agg[m]
        assert float(r["mean"]) == pytest.approx(mean) and float(r["iqm"]) == pytest.approx(iq), m
        assert float(r["optimality_gap"]) == pytest.approx(gap), m
        for stat in ("mean", "iqm", "optimality_gap"):
            assert float(r[f"{stat}_lo"]) <= float(r[stat]) <= float(r[f"{stat}_hi"]), (m, stat)
        assert (
            np.isnan(float(r["paper_mean_normalised"]))
            if paper is None
            else float(r["paper_mean_normalised"]) == pytest.approx(paper)
        )
    assert agg["x"]["env"] == "hopper" and agg["a"]["env"] == "hopper;walker2d" and agg["a"]["runs"] == "6"
    rows = _md_rows(md, "method")
    assert rows["Alg A"][:2] == ["2/2: hopper, walker2d", "6"] and rows["Alg A"][-1] == "1.00"
    assert rows["Extra X (not in Table 9)"][0] == "1/2: hopper" and rows["Extra X (not in Table 9)"][-1] == "–"
    norm = {
        (r["env"], r["method"], r["seed"]): float(r["normalised"])
        for r in csv.DictReader((out / "normalised_scores.csv").open())
    }
    assert norm["walker2d", "a", "2"] == pytest.approx(2.5) and norm["hopper", "b", "0"] == pytest.approx(0.1)
    profile = [r for r in csv.DictReader((out / "normalised_profile.csv").open()) if r["method"] == "Alg A"]
    at_one = min(profile, key=lambda r: abs(float(r["tau"]) - 1.0))
    assert float(at_one["share"]) == np.mean(np.array(a) > float(at_one["tau"]))
    assert (out / "normalised_aggregate.png").read_bytes()[:4] == b"\x89PNG"
    assert re.search(r"!\[normalised aggregate and performance profile\]\(normalised_aggregate.png\)", md)


def test_runs_without_the_tables_row_axis_get_a_sentence(tmp_path):
    from adarl.experiments.report import write_aggregate_report

    root = tmp_path / "runs"
    for seed in (0, 1):
        _fake_run(root, f"algorithm=a__seed={seed}", seed, 0, [(100, 1.0), (200, 2.0)])
    report = {"columns": "algorithm", "paper_table": {**TABLE, "rows": "env"}}
    md = write_aggregate_report([root], tmp_path / "r", report=report).read_text()
    assert "report.paper_table needs runs whose axes are its rows (env) and the column axis (algorithm)" in md
    no_table = write_aggregate_report([root], tmp_path / "r2", report={"columns": "algorithm"}).read_text()
    assert "as the paper prints it" not in no_table and not (tmp_path / "r2" / "paper_table.csv").exists()


def test_a_plateau_per_env_counts_each_rows_seeds_against_its_own_threshold(tmp_path):
    """Issue 45's Table 1 protocol: a seed leaves its env's stand-still plateau above that env's threshold (1500 for
    Hopper, Walker2d and Ant, 5500 for Humanoid), not one number for every env. Per-row counts, the statistics.csv
    threshold of each row, and the spec's check that the mapping names every value of one axis."""
    from adarl.experiments.spec import load_experiment

    # best evaluations: hopper a 110/120/130, b 10/20/30; walker2d a 150/250/350, b 200/210/220
    md, out = _report(tmp_path, plateau={"hopper": 100, "walker2d": 215, "ant": 1})
    rows = {(r["env"], r["algorithm"]): r for r in csv.DictReader((out / "statistics.csv").open())}
    assert {k: (r["above_plateau"], r["plateau"]) for k, r in rows.items()} == {
        ("hopper", "a"): ("3", "100.0"),
        ("hopper", "b"): ("0", "100.0"),
        ("hopper", "x"): ("0", "100.0"),
        ("walker2d", "a"): ("2", "215.0"),
        ("walker2d", "b"): ("1", "215.0"),
    }
    assert "seeds with best eval > its plateau" in md and "3/3 (> 100)" in md and "1/3 (> 215)" in md
    assert "hopper (100), walker2d (215), ant (1)" in md
    with pytest.raises(RecipeError, match=r"report.plateau per value must name every value of one axis"):
        load_experiment(_spec(tmp_path, report={"plateau": {"a": 1}}))  # the algo axis is [a, b]
    assert load_experiment(_spec(tmp_path, report={"plateau": {"a": 1, "b": 2}})).report.plateau == {"a": 1, "b": 2}
