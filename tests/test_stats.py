"""adarl.experiments.report.stats (IQM, stratified bootstrap, probability of improvement) and the aggregate report's
statistics."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml
from test_evaluation_experiments import _fake_run

from adarl.experiments.report.stats import (
    interval_estimate,
    iqm,
    poi_estimate,
    probability_of_improvement,
    stratified_bootstrap,
)


def test_iqm_is_the_mean_of_the_middle_half():
    assert iqm([1, 2, 3, 4]) == pytest.approx(2.5)
    assert iqm([0, 10, 20, 30, 1000, 40, 50, 60]) == pytest.approx(np.mean([20, 30, 40, 50]))  # outliers out
    assert np.isnan(iqm([]))


def test_probability_of_improvement_counts_pairs_and_ties_half():
    assert probability_of_improvement([3, 4], [1, 2]) == 1.0
    assert probability_of_improvement([1, 2], [3, 4]) == 0.0
    assert probability_of_improvement([1, 2], [1, 2]) == 0.5
    assert probability_of_improvement([2, 5], [1, 3, 6]) == pytest.approx(3 / 6)


def test_bootstrap_is_stratified_reproducible_and_covers_the_point():
    rng = np.random.default_rng(0)
    a, b = rng.normal(100, 10, 5), rng.normal(1000, 10, 5)
    # within-task resampling never mixes tasks: each resample keeps 5 runs of each
    seen = stratified_bootstrap(
        [a, b], lambda ts: float(len(ts[0]) == 5 and len(ts[1]) == 5 and ts[0].max() < 500 < ts[1].min()), reps=200
    )
    assert seen.min() == 1.0
    p1 = interval_estimate(a, "iqm", seed=3)
    assert p1 == interval_estimate(a, "iqm", seed=3)  # fixed seed: the same report every time
    assert p1[1] <= p1[0] <= p1[2]
    narrow = interval_estimate(rng.normal(100, 10, 200), "mean")
    assert narrow[2] - narrow[1] < p1[2] - p1[1]
    assert np.isnan(interval_estimate([5.0], "mean")[1])  # one seed: no interval
    pt, lo, hi = poi_estimate([10, 11, 12, 13, 14], [0, 1, 2, 3, 4])
    assert pt == lo == hi == 1.0
    with pytest.raises(ValueError):
        interval_estimate(a, "median")


def test_aggregate_report_statistics_reference_duplicates_and_iterations(tmp_path):
    from adarl.experiments.report import write_aggregate_report

    exp = tmp_path / "exp"
    runs = []
    finals = {"adarl": [300.0, 320.0, 310.0], "sac": [100.0, 150.0, 120.0]}
    for algo, vals in finals.items():
        for seed, v in enumerate(vals):
            rid = f"algorithm={algo}__seed={seed}"
            _fake_run(exp, rid, seed, 0, [(100, v / 3), (200, v / 2), (300, v)])
            runs.append(
                {
                    "run_id": rid,
                    "axes": {"algorithm": algo},
                    "seed": seed,
                    "recipe": "fake",
                    "path": str(exp / rid),
                    "status": "finished",
                }
            )
    # the same seed again (e.g. copied in from another experiment): counted once
    _fake_run(exp, "dup", 0, 0, [(100, 1.0), (300, 9999.0)])
    runs.append(
        {
            "run_id": "dup",
            "axes": {"algorithm": "sac"},
            "seed": 0,
            "recipe": "fake",
            "path": str(exp / "dup"),
            "status": "finished",
        }
    )
    (exp / "experiment.json").write_text(
        json.dumps(
            {
                "name": "fake",
                "axes": ["algorithm"],
                "runs": runs,
                "report": {"columns": "algorithm", "reference": "adarl", "at_updates": [200, 300]},
            }
        )
    )
    md = write_aggregate_report([exp]).read_text()
    out = exp / "report"
    stats = {r["algorithm"]: r for r in csv.DictReader((out / "statistics.csv").open())}
    assert stats["sac"]["n_seeds"] == "3" and float(stats["sac"]["mean"]) == pytest.approx(np.mean(finals["sac"]))
    assert float(stats["sac"]["iqm"]) == pytest.approx(iqm(finals["sac"]))
    assert float(stats["sac"]["poi_ref"]) == 1.0  # every adarl seed above every sac seed
    assert "Seeds found more than once" in md and "seeds [0]" in md
    assert "P(adarl > setting)" in md and "Score at the end of each iteration" in md
    at = [r for r in csv.DictReader((out / "at_updates.csv").open()) if r["algorithm"] == "adarl"]
    assert {int(r["updates"]): float(r["mean"]) for r in at} == {200: pytest.approx(155.0), 300: pytest.approx(310.0)}


def test_rank_settling_reads_the_last_change_and_the_events_after_it(tmp_path):
    from adarl.experiments.report import rank_settling
    from adarl.experiments.report._runs import _load_run

    run = _fake_run(tmp_path, "r", 0, 0, [(100, 1.0), (200, 2.0)])
    history = [
        {
            "step": s,
            "index": i,
            "layers": [
                {"layer": "a", "network": "actor", "old_rank": o, "new_rank": n},
                {"layer": "c", "network": "critic", "old_rank": 8, "new_rank": 8},
            ],
        }
        for i, (s, o, n) in enumerate([(10, 11, 9), (20, 9, 7), (30, 7, 7), (40, 7, 7)])
    ]
    (run / "ranks.json").write_text(json.dumps(history))
    d = rank_settling(_load_run(run, None))
    want = {"initial": 11, "final": 7, "min": 7, "last_change": 20, "events_after": 2, "last_candidate": None}
    assert d["actor:a"] == want
    assert d["critic:c"]["last_change"] is None and d["critic:c"]["events_after"] == 4


def test_runs_csv_has_one_column_per_name_with_an_env_axis(tmp_path):
    """An experiment whose axis is called ``env`` (table1, rank_trajectory) kept two ``env`` columns in runs.csv,
    so csv.DictReader silently lost the axis value."""
    from adarl.experiments.report import write_aggregate_report

    exp = tmp_path / "exp"
    runs = []
    for seed in (0, 1):
        rid = f"env=hopper__seed={seed}"
        _fake_run(exp, rid, seed, 0, [(100, 1.0), (200, 2.0 + seed)])
        runs.append(
            {
                "run_id": rid,
                "axes": {"env": "hopper"},
                "seed": seed,
                "recipe": "fake",
                "path": str(exp / rid),
                "status": "finished",
            }
        )
    (exp / "experiment.json").write_text(json.dumps({"name": "fake", "axes": ["env"], "runs": runs}))
    write_aggregate_report([exp])
    with (exp / "report" / "runs.csv").open() as fh:
        header = next(csv.reader(fh))
        fh.seek(0)
        rows = list(csv.DictReader(fh))
    assert len(header) == len(set(header)), header
    assert {(r["env"], r["env_id"]) for r in rows} == {("hopper", "LinearCartPole-v0")}


def test_event_window_counts_each_seed_once_with_an_interval_and_compares_with_the_reference(tmp_path):
    """The Fig. 9 table: the return dip after each rank event, per seed, refill against reset."""
    from adarl.experiments.report import write_aggregate_report

    exp = tmp_path / "exp"
    runs = []
    dips = {"refill": [-10.0, -12.0, -8.0], "reset": [-50.0, -40.0, -60.0]}
    for mode, values in dips.items():
        for seed, dip in enumerate(values):
            rid = f"warm_start={mode}__seed={seed}"
            run = _fake_run(exp, rid, seed, 0, [(1000, 100.0), (2000, 100.0)])
            scalars = run / "metrics" / "scalars"
            (scalars / "warm_start").mkdir(parents=True)
            (scalars / "train").mkdir(parents=True)
            (scalars / "warm_start" / "frames.csv").write_text("1000,50\n")  # one rank event at frame 1000
            rows = [(f, 100.0) for f in (800, 900, 1000)] + [(f, 100.0 + dip) for f in (1100, 1200)]
            rows.append((1900, 500.0))  # outside the window: ignored
            (scalars / "train" / "episode_return.csv").write_text("".join(f"{f},{v}\n" for f, v in rows))
            runs.append(
                {"run_id": rid, "axes": {"warm_start": mode}, "seed": seed, "recipe": "fake", "path": str(run)}
                | {"status": "finished"}
            )
    (exp / "experiment.json").write_text(
        json.dumps(
            {
                "name": "fake",
                "axes": ["warm_start"],
                "runs": runs,
                "report": {"columns": "warm_start", "reference": "refill", "event_window": 500},
            }
        )
    )
    md = write_aggregate_report([exp]).read_text()
    section = md.split("## Training return around rank events", 1)[1]
    line = next(row for row in section.splitlines() if row.startswith("| warm_start=reset |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1:4] == ["3", "3", "-50.0"]  # events, seeds, mean change
    assert cells[4].startswith("-50.0 [") and cells[-2] == "1.00 [1.00, 1.00]"  # every refill seed dips less
    assert cells[-1] == "refill beats reset"  # the decision rule: the interval excludes 0.5
    with (exp / "report" / "event_window.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 6


def test_score_is_the_mean_of_the_last_evaluations_with_plateau_counts_and_verdicts(tmp_path):
    """Issue 34's protocol: a run scores the mean of its last three evaluations; the report counts the seeds whose
    best evaluation left the plateau and states the decision rule's verdict for each setting against the
    reference."""
    from adarl.experiments.report import verdict, write_aggregate_report

    exp = tmp_path / "exp"
    curves = {  # the last three evaluations decide, not the last one alone
        "adarl": [[100, 2000, 1600, 1700, 1800], [100, 900, 1700, 1600, 1500], [100, 1000, 1400, 1500, 1600]],
        "sac": [[100, 3000, 900, 1000, 1100], [100, 1000, 1000, 1000, 1000], [100, 1100, 1000, 900, 1000]],
    }
    runs = []
    for algo, per_seed in curves.items():
        for seed, vals in enumerate(per_seed):
            rid = f"algorithm={algo}__seed={seed}"
            _fake_run(exp, rid, seed, 0, [(100 * (i + 1), v) for i, v in enumerate(vals)])
            runs.append(
                {"run_id": rid, "axes": {"algorithm": algo}, "seed": seed, "recipe": "f", "path": str(exp / rid)}
            )
    report = {"columns": "algorithm", "reference": "adarl", "score_last": 3, "plateau": 1500}
    (exp / "experiment.json").write_text(
        json.dumps({"name": "f", "axes": ["algorithm"], "runs": runs, "report": report})
    )
    md = write_aggregate_report([exp]).read_text()
    out = exp / "report"
    rows = {(r["algorithm"], r["seed"]): r for r in csv.DictReader((out / "runs.csv").open())}
    assert (
        float(rows["adarl", "0"]["score"]) == pytest.approx(1700.0) and rows["adarl", "0"]["final_return"] == "1800.0"
    )
    assert float(rows["sac", "0"]["best_eval"]) == 3000.0 and rows["sac", "0"]["score_last"] == "3"
    stats = {r["algorithm"]: r for r in csv.DictReader((out / "statistics.csv").open())}
    assert float(stats["adarl"]["mean"]) == pytest.approx(np.mean([1700, 1600, 1500]))
    assert stats["adarl"]["above_plateau"] == "3" and stats["sac"]["above_plateau"] == "1"  # best > 1500
    assert float(stats["sac"]["poi_ref"]) == 1.0 and "adarl beats sac" in md and "3/3" in md and "1/3" in md
    assert stats["sac"]["verdict"] == "adarl beats sac" and stats["adarl"]["verdict"] == ""  # the rule's words too
    assert "the mean of its last 3 evaluations" in md and (out / "learning_curves_by_seed.png").is_file()
    assert verdict((0.5, 0.2, 0.8), "a", "b") == "no difference shown"
    assert verdict((0.1, 0.0, 0.45), "a", "b") == "b beats a"


def test_loose_run_folders_report_by_an_experiments_rule_given_on_the_command_line(tmp_path, capsys):
    """Run folders copied out of an experiment (no experiment.json: e.g. a committed report's runs/) keep their axes
    from their run ids, and ``adarl report --set`` gives them the experiment's rule, so the report re-derives the
    experiment's own statistics; a bad option is refused before anything is written."""
    import shutil

    from adarl.cli import main
    from adarl.experiments.report import write_aggregate_report

    exp, loose = tmp_path / "exp", tmp_path / "runs"
    runs = []
    for algo, per_seed in {
        "adarl": [[100, 2000, 1700], [100, 900, 1400]],
        "sac": [[100, 1000, 900], [100, 80, 90]],
    }.items():
        for seed, vals in enumerate(per_seed):
            rid = f"env=hopper__algorithm={algo}__seed={seed}"
            _fake_run(exp, rid, seed, 0, [(100 * (i + 1), v) for i, v in enumerate(vals)])
            runs.append(
                {"run_id": rid, "axes": {"env": "hopper", "algorithm": algo}, "seed": seed, "path": str(exp / rid)}
            )
            shutil.copytree(exp / rid, loose / rid)
    report = {"columns": "algorithm", "reference": "adarl", "score_last": 2, "plateau": 1500.0}  # as model_dump()
    (exp / "experiment.json").write_text(
        json.dumps({"name": "f", "axes": ["env", "algorithm"], "runs": runs, "report": report})
    )
    write_aggregate_report([exp])

    def stats(folder):
        return {r["algorithm"]: r for r in csv.DictReader((folder / "statistics.csv").open())}

    rule = ["--set", "score_last=2", "--set", "plateau=1500", "--set", "reference=adarl"]
    pairs = ["--set", "pairs=[[sac, adarl]]"]
    assert main(["report", str(loose), "-o", str(tmp_path / "loose"), *rule, *pairs]) == 0
    assert stats(tmp_path / "loose") == stats(exp / "report")  # scores, plateau counts, P(adarl > sac), verdicts
    # report.pairs: P(a > b) between two arms (here the reference's comparison turned round), with the rule's verdict
    compared = list(csv.DictReader((tmp_path / "loose" / "pairs.csv").open()))
    assert [(r["a"], r["b"], r["n_a"], r["n_b"]) for r in compared] == [("sac", "adarl", "2", "2")]
    assert float(compared[0]["poi"]) == pytest.approx(1 - float(stats(exp / "report")["sac"]["poi_ref"]))
    assert compared[0]["verdict"] == "adarl beats sac"
    md = (tmp_path / "loose" / "report.md").read_text()
    assert 'score_last=2, plateau=1500.0, reference="adarl", pairs=[["sac", "adarl"]]' in md
    # --spec: an experiment spec's report section (here the experiment's own), --set over it
    spec = tmp_path / "spec.yaml"
    axes = {"env": ["hopper"], "algorithm": ["adarl", "sac", "later"]}  # "later": an arm not run yet
    spec.write_text(
        yaml.safe_dump({"kind": "experiment", "name": "f", "recipe": "quickstart", "axes": axes, "report": report})
    )
    assert main(["report", str(loose), "-o", str(tmp_path / "by_spec"), "--spec", str(spec)]) == 0
    assert stats(tmp_path / "by_spec") == stats(exp / "report")
    assert main(["report", str(loose), "-o", str(tmp_path / "over"), "--spec", str(spec), "--set", "score_last=1"]) == 0
    assert float(stats(tmp_path / "over")["adarl"]["mean"]) == pytest.approx((1700 + 1400) / 2)  # the last evaluation
    # a pair may name the spec's arm that has no runs yet (a stage in progress): said in its row, not refused
    later = ["--spec", str(spec), "--set", "pairs=[[sac, later]]"]
    assert main(["report", str(loose), "-o", str(tmp_path / "later"), *later]) == 0
    (row,) = csv.DictReader((tmp_path / "later" / "pairs.csv").open())
    assert (row["n_a"], row["n_b"], row["verdict"]) == ("2", "0", "no finished runs of later")
    # verdict_seeds: the seeds a protocol planned; runs landing one by one give P as an interim estimate, no verdict
    waits = ["--set", "verdict_seeds=3", *pairs]
    assert main(["report", str(loose), "-o", str(tmp_path / "waits"), *rule, *waits]) == 0
    waiting, decided = stats(tmp_path / "waits"), stats(exp / "report")
    assert waiting["sac"].pop("verdict") == "waits for 3 seeds each (has 2 and 2)"
    assert decided["sac"].pop("verdict") == "adarl beats sac"
    assert waiting == decided  # the same P and intervals
    (row,) = csv.DictReader((tmp_path / "waits" / "pairs.csv").open())
    assert row["verdict"] == "waits for 3 seeds each (has 2 and 2)"
    md = (tmp_path / "waits" / "report.md").read_text()
    assert "| waits for 3 seeds each (has 2 and 2) |" in md and "adarl beats sac" not in md
    assert main(["report", str(loose), "-o", str(tmp_path / "enough"), *rule, "--set", "verdict_seeds=2", *pairs]) == 0
    (row,) = csv.DictReader((tmp_path / "enough" / "pairs.csv").open())
    assert row["verdict"] == "adarl beats sac"
    # per arm (a protocol planned 8 of one arm and 5 of another): each side waits for its own count
    per_arm = ["--set", "verdict_seeds={adarl: 2, sac: 3}", *pairs]
    assert main(["report", str(loose), "-o", str(tmp_path / "per_arm"), *rule, *per_arm]) == 0
    (row,) = csv.DictReader((tmp_path / "per_arm" / "pairs.csv").open())
    assert row["verdict"] == "waits for 3 and 2 seeds (has 2 and 2)"  # P(sac > adarl): sac's 3, adarl's 2
    md = " ".join((tmp_path / "per_arm" / "report.md").read_text().split())
    assert "| 1.00 [1.00, 1.00] | waits for 2 and 3 seeds (has 2 and 2) |" in md  # P(adarl > sac): adarl's 2, sac's 3
    assert "only once both sides have their planned seeds (adarl 2, sac 3)" in md
    met = ["--set", "verdict_seeds={adarl: 2, sac: 2}", *pairs]
    assert main(["report", str(loose), "-o", str(tmp_path / "met"), *rule, *met]) == 0
    (row,) = csv.DictReader((tmp_path / "met" / "pairs.csv").open())
    assert row["verdict"] == "adarl beats sac"
    # ... and the spec's arm with no runs yet may have its count, given on the command line or in the spec itself
    later_count = ["--spec", str(spec), "--set", "verdict_seeds={adarl: 2, sac: 2, later: 5}"]
    assert main(["report", str(loose), "-o", str(tmp_path / "later_count"), *later_count]) == 0
    own = tmp_path / "own.yaml"
    own.write_text(
        yaml.safe_dump(
            {
                "kind": "experiment",
                "name": "f",
                "recipe": "quickstart",
                "axes": axes,
                "report": {**report, "verdict_seeds": {"adarl": 2, "sac": 3, "later": 5}},
            }
        )
    )
    assert main(["report", str(loose), "-o", str(tmp_path / "own"), "--spec", str(own)]) == 0
    assert "| waits for 2 and 3 seeds (has 2 and 2) |" in (tmp_path / "own" / "report.md").read_text()
    # an experiment's own report (its mapping checked against its spec, whose budget may not run every arm)
    write_aggregate_report([exp], tmp_path / "exp_own", report={"verdict_seeds": {"adarl": 2, "sac": 2, "later": 5}})
    assert "adarl beats sac" in (tmp_path / "exp_own" / "report.md").read_text()
    for bad, said in [
        (["--set", "score_lst=2"], "did you mean 'score_last'"),
        (["--set", "score_last=0"], "score_last: Input should be greater than or equal to 1"),
        (["--set", "plateau"], "must be KEY=VALUE"),
        (["--set", "pairs=[[sac, sac]]"], "a pair compares two different values"),
        (["--set", "pairs=[sac, adarl]"], "pairs.0"),
        # a value of no run and no spec: a typo, refused with the values there are
        (["--set", "pairs=[[sac, adrl]]"], "report.pairs name ['adrl'], not values of the column axis 'algorithm'"),
        (["--spec", str(spec), "--set", "pairs=[[sac, adrl]]"], "in these runs or the spec: ['adarl', 'later', 'sac']"),
        (["--spec", str(tmp_path / "nope.yaml")], "experiment spec"),
        # a per-arm count that leaves an arm out would let it decide with no planned count; a typo names the arms
        (["--set", "verdict_seeds={adarl: 8}"], "report.verdict_seeds has no seed count for ['sac']; the arms:"),
        (["--set", "verdict_seeds={adarl: 8, sac: 8, sca: 5}"], "names ['sca'], not values of the column axis"),
        (["--set", "verdict_seeds={adarl: 1, sac: 8}"], "greater than or equal to 2"),
    ]:
        capsys.readouterr()
        assert main(["report", str(loose), "-o", str(tmp_path / "refused"), *bad]) == 2
        assert said in capsys.readouterr().err
        assert not (tmp_path / "refused").exists()


def test_axes_from_run_id():
    from adarl.experiments.report import axes_from_run_id

    assert axes_from_run_id("env=hopper__algorithm=adarl__seed=3", 3) == {"env": "hopper", "algorithm": "adarl"}
    assert axes_from_run_id("env=hopper__algorithm=adarl__seed=3", 4) is None  # the id's seed is not the recipe's
    for name in ("seed=3", "hopper_adarl", "env=hopper__seed", "env=hopper__x__seed=3", "env=hopper__algorithm=a"):
        assert axes_from_run_id(name, 3) is None, name


def test_interval_and_poi_estimates_are_the_bootstraps_resample_by_resample():
    """The estimates compute their statistic on all resamples at once; the resamples and the result are exactly
    those of one resample at a time (stratified_bootstrap's draws), so committed reports do not move."""
    rng = np.random.default_rng(7)
    lo, hi = (1 - 0.95) / 2, 1 - (1 - 0.95) / 2  # the quantiles as the estimators compute them
    for trial in range(40):
        tasks = [
            rng.normal(0, 100, rng.integers(1, 10)).round(int(rng.integers(0, 2))) for _ in range(rng.integers(1, 4))
        ]
        other = [rng.normal(0, 100, rng.integers(1, 10)).round(0) for _ in tasks]
        x, y = (tasks[0], other[0]) if len(tasks) == 1 else (tasks, other)
        for stat, fn in (("iqm", iqm), ("mean", np.mean)):
            if sum(t.size for t in tasks) < 2:
                continue
            draws = np.random.default_rng(trial)  # one resample at a time, each task in order (rliable's order)
            boot = [fn(np.concatenate([t[draws.integers(0, t.size, t.size)] for t in tasks])) for _ in range(200)]
            want = (fn(np.concatenate(tasks)), np.quantile(boot, lo), np.quantile(boot, hi))
            assert interval_estimate(x, stat, reps=200, seed=trial) == tuple(map(float, want)), (trial, stat)
        draws = np.random.default_rng(trial)
        boot = []
        for _ in range(200):
            per_task = []
            for a, b in zip(tasks, other):
                ra = a[draws.integers(0, a.size, a.size)]
                per_task.append(probability_of_improvement(ra, b[draws.integers(0, b.size, b.size)]))
            boot.append(np.mean(per_task))
        point = np.mean([probability_of_improvement(a, b) for a, b in zip(tasks, other)])
        want = (point, np.quantile(boot, lo), np.quantile(boot, hi))
        assert poi_estimate(x, y, reps=200, seed=trial) == tuple(map(float, want)), trial
