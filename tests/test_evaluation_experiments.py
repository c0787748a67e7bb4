"""Linear CartPole (paper Eq. 17), robustness sweeps, experiment specs and the aggregate report."""

from __future__ import annotations

import csv
import json
import math
import shutil
import statistics
from pathlib import Path

import pytest
import torch
import yaml
from _helpers import adarl, tiny

from adarl.errors import AdaRLValueError, RecipeError

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------- linear CartPole
def test_linear_cartpole_matrices_are_eq17_and_rank_4():
    from adarl.envs import linear_cartpole_matrices

    m, M, g, l = 0.1, 1.0, 9.8, 0.5
    d = 4 / 3 - m / (m + M)
    A, B = linear_cartpole_matrices(l)
    assert A[1, 2].item() == pytest.approx(-m * g / ((m + M) * d))
    assert A[3, 2].item() == pytest.approx(g / (l * d))
    assert B[1].item() == pytest.approx(1 / (m + M) + m / ((m + M) ** 2 * d))
    assert B[3].item() == pytest.approx(-1 / (l * (m + M) * d))
    # The Euler transition [I + tau A | tau B] has rank 4 (the paper's intrinsic rank); A alone has rank 3.
    step = torch.cat([torch.eye(4, dtype=A.dtype) + 0.02 * A, 0.02 * B[:, None]], dim=1)
    assert torch.linalg.matrix_rank(step).item() == 4
    # Longer poles fall more slowly.
    assert linear_cartpole_matrices(0.6)[0][3, 2] < A[3, 2]


def test_linear_cartpole_env_batched_with_pole_length_range():
    from torchrl.envs.utils import check_env_specs

    from adarl.envs import LinearCartPoleEnv

    env = LinearCartPoleEnv(batch_size=(4,), pole_length_range=(0.475, 0.525), seed=3)
    check_env_specs(env)
    td = env.rollout(300, break_when_any_done=False)
    assert td.shape == (4, 300)
    lengths = env.pole_length
    assert ((lengths >= 0.475) & (lengths <= 0.525)).all() and lengths.unique().numel() == 4
    assert td["next", "done"].any()  # a random policy drops the pole
    with pytest.raises(AdaRLValueError, match="pole_length_range"):
        LinearCartPoleEnv(pole_length_range=(0.5, 0.4))


def test_linear_cartpole_through_make_env_follows_the_schedule():
    from adarl.envs import make_env, make_eval_env

    env = make_env("LinearCartPole-v0", preset="paper", seed=0)
    drawn = [float(env.rollout(5)["dynamics", "pole_length"][0]) for _ in range(6)]
    assert all(0.475 <= x <= 0.525 for x in drawn) and len(set(drawn)) == 6
    short, long = (make_eval_env("LinearCartPole-v0", values={"pole_length": v}, seed=0) for v in (0.3, 0.9))
    a, b = short.rollout(20), long.rollout(20)
    assert float(a["dynamics", "pole_length"][0]) == pytest.approx(0.3)
    assert float(b["dynamics", "pole_length"][0]) == pytest.approx(0.9)


# ------------------------------------------------------------------------------------------- sweeps
def test_parse_sweep():
    from adarl.experiments.sweep import parse_sweep

    assert parse_sweep("torso_length=0.25:0.55:7") == (
        "torso_length",
        pytest.approx([0.25 + 0.05 * i for i in range(7)]),
    )
    assert parse_sweep("wind=0,1.5") == ("wind", [0.0, 1.5])
    for bad in ("torso_length", "=1:2:3", "x=1:2", "x=a:b:3", "x=1:2:0", "x=nan,1"):
        with pytest.raises(AdaRLValueError, match="sweep"):
            parse_sweep(bad)


# ------------------------------------------------------------------------------------------- experiment specs
def _spec(tmp_path: Path, **extra) -> Path:
    data = {
        "kind": "experiment",
        "name": "t",
        "recipe": "linear_cartpole_sac",
        "axes": {"algo": [{"name": "a"}, {"name": "b", "overrides": ["rank.enabled=false"]}]},
        "seeds": [0, 1],
    }
    data.update(extra)
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_experiment_spec_errors_name_the_key(tmp_path):
    from adarl.experiments.spec import load_experiment

    with pytest.raises(RecipeError, match="seedz"):
        load_experiment(_spec(tmp_path, seedz=[1]))
    with pytest.raises(RecipeError, match="not an experiment spec"):
        load_experiment(_spec(tmp_path, kind="recipe"))
    with pytest.raises(RecipeError, match="distinct"):
        load_experiment(_spec(tmp_path, seeds=[1, 1]))
    with pytest.raises(RecipeError, match="no value"):
        load_experiment(_spec(tmp_path, budgets={"small": {"axes": {"algo": ["zzz"]}}}))
    with pytest.raises(RecipeError, match="x_axis"):
        load_experiment(_spec(tmp_path, report={"x_axis": "rank"}))
    with pytest.raises(RecipeError, match=r"report.pairs name \['c'\], not values of the column axis 'algo'"):
        load_experiment(_spec(tmp_path, report={"columns": "algo", "pairs": [["a", "c"]]}))
    with pytest.raises(RecipeError, match="a pair compares two different values"):
        load_experiment(_spec(tmp_path, report={"columns": "algo", "pairs": [["a", "a"]]}))
    assert load_experiment(_spec(tmp_path, report={"columns": "algo", "pairs": [["b", "a"]]})).report.pairs == [
        ("b", "a")
    ]
    # per-arm planned seeds: every arm named once (an arm left out would decide with no planned count)
    with pytest.raises(RecipeError, match=r"report.verdict_seeds per arm must name each value of the column axis"):
        load_experiment(_spec(tmp_path, report={"columns": "algo", "verdict_seeds": {"a": 8}}))
    with pytest.raises(RecipeError, match=r"verdict_seeds"):
        load_experiment(_spec(tmp_path, report={"columns": "algo", "verdict_seeds": {"a": 8, "b": 5, "c": 5}}))
    with pytest.raises(RecipeError, match=r"report.verdict_seeds per arm needs a column axis"):
        load_experiment(_spec(tmp_path, report={"verdict_seeds": {"a": 8, "b": 5}}))
    per_arm = load_experiment(_spec(tmp_path, report={"columns": "algo", "verdict_seeds": {"a": 8, "b": 5}}))
    assert per_arm.report.verdict_seeds == {"a": 8, "b": 5}


def test_plan_runs_product_budget_and_templates(tmp_path):
    from adarl.experiments.spec import load_experiment, plan_runs

    spec = load_experiment(
        _spec(
            tmp_path,
            overrides=["name=run_{algo}_{seed}"],
            budgets={"small": {"seeds": [5], "axes": {"algo": ["b"]}, "overrides": ["collector.total_frames=100"]}},
        )
    )
    runs = plan_runs(spec, tmp_path / "out")
    assert [r.run_id for r in runs] == ["algo=a__seed=0", "algo=a__seed=1", "algo=b__seed=0", "algo=b__seed=1"]
    assert runs[2].overrides == ["name=run_b_0", "rank.enabled=false", "seed=0"]
    small = plan_runs(spec, tmp_path / "out", "small")
    assert [r.run_id for r in small] == ["algo=b__seed=5"]
    assert small[0].overrides[-2:] == ["collector.total_frames=100", "seed=5"]
    bad = load_experiment(_spec(tmp_path, overrides=["name=run_{sede}"]))
    with pytest.raises(RecipeError, match="sede"):
        plan_runs(bad, tmp_path / "out")
    with pytest.raises(RecipeError, match="no budget"):
        plan_runs(spec, tmp_path / "out", "huge")


def test_shipped_experiment_specs_validate_and_are_not_recipes():
    from adarl.experiments.spec import load_experiment, plan_runs
    from adarl.runtime.config import list_recipes, load_recipe

    specs = sorted((REPO / "recipes" / "experiments").glob("*.yaml"))
    assert {p.stem for p in specs} >= {
        "table1",
        "table2",
        "cartpole_rank_sweep",
        "warmstart_ablation",
        "rule_ablation",
        "hopper_sweep",
    }
    assert not any(name.startswith("experiments/") for name, _ in list_recipes())
    for p in specs:
        spec = load_experiment(p)
        assert "small" in spec.budgets and spec.budgets["small"].description
        # the 2-core reproduction: `laptop`; table1's is issue 34's two stages, `pilot` and `decisive`; issue 45's
        # mechanism arms run at the pilot's budget (`pilot`)
        budgets = {"table1": ["pilot", "decisive"], "mechanism": ["pilot"]}
        for name in budgets.get(p.stem, ["laptop"]):
            assert name in spec.budgets and spec.budgets[name].description, (p.stem, name)
        for run in (r for budget in spec.budgets for r in plan_runs(spec, "/nonexistent", budget)):
            try:
                load_recipe(run.recipe, run.overrides)
            except RecipeError as err:  # only a recipe from another branch may be missing
                assert f"no recipe named {run.recipe!r}" in str(err) and run.recipe.startswith("baselines/")


# ------------------------------------------------------------------------------------------- aggregation
def _fake_run(root: Path, name: str, seed: int, rank: int, evals: list[tuple[int, float]]) -> Path:
    p = root / name
    p.mkdir(parents=True)
    (p / "recipe.yaml").write_text(
        yaml.safe_dump(
            {
                "name": "fake",
                "seed": seed,
                "env": {"id": "LinearCartPole-v0"},
                "collector": {"total_frames": evals[-1][0]},
            }
        )
    )
    with (p / "eval.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frames", "updates", "mean", "std", "ci95", "episodes", "returns", "ranks"])
        for f, m in evals:
            w.writerow([f, f, m, 1.0, 2.0, 2, json.dumps([m - 1, m + 1]), "{}"])
    (p / "summary.json").write_text(json.dumps({"frames": evals[-1][0], "updates": evals[-1][0]}))
    return p


def test_aggregate_table_matches_runs(tmp_path):
    from adarl.experiments.report import aggregate_runs, write_aggregate_report

    exp = tmp_path / "exp"
    runs = []
    finals = {1: [10.0, 30.0], 4: [100.0, 120.0], 8: [90.0, 50.0]}
    for rank, vals in finals.items():
        for seed, v in enumerate(vals):
            rid = f"rank={rank}__seed={seed}"
            _fake_run(exp, rid, seed, rank, [(100, 1.0), (200, v)])
            runs.append(
                {
                    "run_id": rid,
                    "axes": {"rank": str(rank)},
                    "seed": seed,
                    "recipe": "fake",
                    "path": str(exp / rid),
                    "status": "finished",
                }
            )
    runs.append(
        {
            "run_id": "rank=2__seed=0",
            "axes": {"rank": "2"},
            "seed": 0,
            "recipe": "nope",
            "path": str(exp / "x"),
            "status": "missing-recipe",
        }
    )
    (exp / "experiment.json").write_text(
        json.dumps({"name": "fake", "axes": ["rank"], "runs": runs, "report": {"x_axis": "rank", "intrinsic_rank": 4}})
    )
    agg = aggregate_runs([exp])
    for rank, vals in finals.items():
        g = agg.group(rank=rank)
        assert g.finals == vals
        assert g.mean == pytest.approx(statistics.fmean(vals)) and g.std == pytest.approx(statistics.stdev(vals))
    md = write_aggregate_report([exp]).read_text()
    assert "**110.0 ± 14.1 (n=2)**" in md and "20.0 ± 14.1 (n=2)" in md
    assert "rank=2__seed=0 (nope)" in md
    out = exp / "report"
    with (out / "table.csv").open() as fh:
        rows = {r["rank"]: r for r in csv.DictReader(fh)}
    assert float(rows["8"]["mean"]) == pytest.approx(70.0) and rows["8"]["n_seeds"] == "2"
    with (out / "return_vs_rank.csv").open() as fh:
        assert [r["rank"] for r in csv.DictReader(fh)] == ["1", "4", "8"]
    for png in ("return_vs_rank.png", "learning_curves.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    assert "<table>" in (out / "report.html").read_text()


def test_budgets_run_into_one_folder_are_all_reported_and_never_pooled(tmp_path):
    """Two budgets of a spec run into one output folder: experiment.json keeps the earlier budget's record (under
    ``earlier``; the same budget run again replaces its own), so that a report over the folder has every budget's runs,
    not only the last one's; where two budgets ran the same setting (other seeds, other frames), a ``budget`` axis
    keeps them apart instead of pooling them as replicates of one setting."""
    from adarl.experiments.launchers import LocalLauncher
    from adarl.experiments.orchestrate import run_experiment
    from adarl.experiments.report import collect_runs
    from adarl.runtime.config import load_recipe
    from adarl.runtime.config.dump import save_resolved

    class FakeTraining(LocalLauncher):  # each run "trains" into a finished run folder of its recipe, scoring its seed
        def launch(self, runs, on_done, *, tick=lambda running: None):
            for run in runs:
                recipe = load_recipe(run.recipe, run.overrides)
                frames = recipe.collector.total_frames
                _fake_run(Path(run.path).parent, Path(run.path).name, run.seed, 4, [(frames, float(run.seed))])
                save_resolved(recipe, Path(run.path) / "recipe.yaml")  # what the spec plans: reused when planned again
                run.status = "finished"
                on_done(run)

    spec = {
        "kind": "experiment",
        "name": "twobudgets",
        "recipe": "linear_cartpole_sac",
        "overrides": TINY,
        "axes": {"algorithm": [{"name": "a"}, {"name": "b", "overrides": ["rank.enabled=false"]}]},
        "seeds": [0, 1],
        "budgets": {
            "first": {"axes": {"algorithm": ["a"]}},
            "second": {"axes": {"algorithm": ["b"]}},
            "more_a": {"axes": {"algorithm": ["a"]}, "seeds": [2, 3]},
        },
    }
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / "exp"
    quiet = dict(output=out, report=False, log=lambda *_: None, launcher=FakeTraining())
    for budget in ("first", "second"):
        run_experiment(path, budget=budget, **quiet)
    state = json.loads((out / "experiment.json").read_text())
    assert state["budget"] == "second" and [e["budget"] for e in state["earlier"]] == ["first"]
    runs, info = collect_runs([out])
    assert sorted((r.axes["algorithm"], r.seed) for r in runs) == [("a", 0), ("a", 1), ("b", 0), ("b", 1)]
    assert all("budget" not in r.axes for r in runs)  # one budget per setting: nothing to keep apart
    assert [e["budget"] for e in info["experiments"]] == ["first", "second"]
    run_experiment(path, budget="second", **quiet)  # the same budget again replaces its own record
    state = json.loads((out / "experiment.json").read_text())
    assert [e["budget"] for e in state["earlier"]] == ["first"]
    (out / "experiment.json").write_text("{not json")  # a damaged record: kept beside, named, a new one written
    said: list[str] = []
    run_experiment(path, budget="second", **{**quiet, "log": said.append})
    (kept,) = out.glob("experiment.json.unreadable-*")
    assert kept.read_text() == "{not json" and any(kept.name in line for line in said)
    assert json.loads((out / "experiment.json").read_text())["budget"] == "second"
    (out / "experiment.json").write_text(json.dumps(state))  # the record as it was
    run_experiment(path, budget="more_a", **quiet)  # arm a again, other seeds: never pooled with the first's
    state = json.loads((out / "experiment.json").read_text())
    assert [e["budget"] for e in state["earlier"]] == ["first", "second"]
    runs, _ = collect_runs([out])
    assert sorted((r.axes["algorithm"], r.axes["budget"], r.seed) for r in runs) == [
        ("a", "twobudgets:first", 0),
        ("a", "twobudgets:first", 1),
        ("a", "twobudgets:more_a", 2),
        ("a", "twobudgets:more_a", 3),
        ("b", "twobudgets:second", 0),
        ("b", "twobudgets:second", 1),
    ]


# ------------------------------------------------------------------------------------------- end to end
TINY = tiny()


@pytest.mark.slow
def test_experiment_end_to_end_two_seeds_two_algorithms(tmp_path):
    spec = {
        "kind": "experiment",
        "name": "tiny",
        "recipe": "linear_cartpole_sac",
        "overrides": TINY,
        "axes": {
            "algorithm": [
                {"name": "adarl"},
                {
                    "name": "fixed4",
                    "overrides": ["rank.enabled=false", "network.actor.rank=4", "network.critic.rank=4"],
                },
                {"name": "notyet", "recipe": "baselines/linear_cartpole_nothing"},
            ]
        },
        "seeds": [0, 1],
        "workers": 2,
        "sweeps": [{"params": ["pole_length=0.4,0.6"], "episodes": 1, "name": "pole"}],
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / "exp"
    proc = adarl("experiment", str(path), "-o", str(out), timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "4 finished" in proc.stdout and "2 missing-recipe" in proc.stdout
    state = json.loads((out / "experiment.json").read_text())
    assert sorted(r["status"] for r in state["runs"]) == ["finished"] * 4 + ["missing-recipe"] * 2
    # The aggregated table is exactly the individual runs' last evaluations.
    finals: dict[str, list[float]] = {}
    for r in state["runs"]:
        if r["status"] == "finished":
            with (Path(r["path"]) / "eval.csv").open() as fh:
                finals.setdefault(r["axes"]["algorithm"], []).append(float(list(csv.DictReader(fh))[-1]["mean"]))
            assert (Path(r["path"]) / "sweeps" / "pole.csv").is_file()
    with (out / "report" / "table.csv").open() as fh:
        table = {r["algorithm"]: r for r in csv.DictReader(fh)}
    assert set(table) == {"adarl", "fixed4"}
    for algo, vals in finals.items():
        assert float(table[algo]["mean"]) == pytest.approx(statistics.fmean(vals))
        assert float(table[algo]["std"]) == pytest.approx(statistics.stdev(vals))
        assert table[algo]["n_seeds"] == "2"
    md = (out / "report" / "report.md").read_text()
    best = max(finals, key=lambda a: statistics.fmean(finals[a]))
    assert f"**{statistics.fmean(finals[best]):.1f} ± {statistics.stdev(finals[best]):.1f} (n=2)**" in md
    assert "Robustness sweep: pole" in md and "Rank trajectories" in md
    for png in ("learning_curves.png", "ranks.png", "sweep_pole.png"):
        assert (out / "report" / png).is_file()
    # Resumable: a second call runs nothing new (in-process: it only plans, validates and skips).
    from adarl.experiments.orchestrate import run_experiment
    from adarl.experiments.report import write_aggregate_report

    said: list[str] = []
    again = run_experiment(path, output=out, report=False, log=said.append)
    assert sorted(r.status for r in again) == ["missing-recipe"] * 2 + ["skipped-finished"] * 4
    assert "4 already finished, 0 to run" in said[-1]
    # Aggregating the run folders directly (no experiment.json) groups them by the axes their run ids name; copies
    # under other names by recipe name, and runs of one recipe with other settings apart (a variant naming the keys
    # that differ): never four replicates of one setting
    finished = [Path(r["path"]) for r in state["runs"] if r["status"] == "finished"]
    by_id = write_aggregate_report(finished, tmp_path / "by_id").read_text()
    assert "(n=4)" not in by_id and by_id.count("(n=2)") >= 2 and "| fixed4 |" in by_id.replace("**", "")
    copies = []
    for i, run in enumerate(finished):
        copies.append(tmp_path / "copies" / f"run{i}")
        shutil.copytree(run, copies[-1], ignore=shutil.ignore_patterns("checkpoints"))
    loose = write_aggregate_report(copies, tmp_path / "loose").read_text()
    assert "(n=4)" not in loose and loose.count("(n=2)") >= 2 and "rank.enabled=False" in loose


@pytest.mark.slow
def test_hopper_sweep_writes_fig8_plot_and_worst_case(tmp_path):
    from adarl.experiments.sweep import parse_sweep, sweep_run
    from adarl.runtime.config import load_recipe, save_resolved
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import OffPolicyTrainer

    run = tmp_path / "hopper"
    hopper_tiny = [o for o in TINY if not o.startswith("eval.max_steps")] + ["eval.max_steps=40"]
    recipe = load_recipe("quickstart", hopper_tiny)
    run_dir = RunDir.create(run)
    save_resolved(recipe, run_dir.recipe_path)
    OffPolicyTrainer(recipe, run_dir, quiet=True).train()
    result = sweep_run(run, [parse_sweep("torso_length=0.25:0.55:3")], episodes=2)
    assert "worst episode" in result.describe()
    rows = list(csv.DictReader((run / "sweeps" / "torso_length.csv").open()))
    assert [float(r["torso_length"]) for r in rows] == pytest.approx([0.25, 0.4, 0.55])
    summary = json.loads((run / "sweeps" / "torso_length.json").read_text())
    every = [x for r in rows for x in json.loads(r["returns"])]
    assert summary["worst_case"] == pytest.approx(min(every))
    assert summary["average"] == pytest.approx(statistics.fmean(float(r["mean"]) for r in rows))
    assert summary["nominal"] == {"foot_length": pytest.approx(0.39)}  # the other parameter at the schedule centre
    assert (run / "sweeps" / "torso_length.png").read_bytes()[:4] == b"\x89PNG"
    bad = adarl("eval", str(run), "--sweep", "pole_length=0.1:0.2:2", timeout=900)
    assert bad.returncode == 2 and "unknown sweep parameter 'pole_length'" in bad.stderr
    assert not math.isnan(summary["worst_mean"])


def test_an_axis_value_may_run_fewer_seeds_than_its_budget():
    """table1's pilot: fixed_final and Parseval run seeds 0-4 beside arms at seeds 0-7 (issue 34)."""
    from adarl.experiments.spec import ExperimentSpec, load_experiment, plan_runs

    spec = ExperimentSpec.model_validate(
        {
            "kind": "experiment",
            "name": "x",
            "recipe": "quickstart",
            "seeds": [0, 1, 2],
            "axes": {"arm": ["a", {"name": "b", "seeds": [1, 5]}]},
        }
    )
    assert [(r.axes["arm"], r.seed) for r in plan_runs(spec, "/x")] == [("a", 0), ("a", 1), ("a", 2), ("b", 1)]
    pilot = plan_runs(load_experiment("table1"), "/x", "pilot")
    per_arm = {
        a: sorted(r.seed for r in pilot if r.axes["algorithm"] == a) for a in {r.axes["algorithm"] for r in pilot}
    }
    assert per_arm["adarl"] == per_arm["sac_full"] == per_arm["sac_restarts"] == list(range(8))
    assert per_arm["fixed_final"] == per_arm["parseval"] == list(range(5))


def test_a_budget_may_give_a_value_other_seeds():
    """``value_seeds``: a budget replaces a value's own seeds (null: all the budget's), e.g. stage 2 of issue 34 runs
    Parseval at 8 seeds where the pilot ran it at 5; an unknown axis or value is refused, naming the known ones."""
    from pydantic import ValidationError

    from adarl.experiments.spec import ExperimentSpec, load_experiment, plan_runs

    def spec(value_seeds):
        return ExperimentSpec.model_validate(
            {
                "kind": "experiment",
                "name": "x",
                "recipe": "quickstart",
                "seeds": [0, 1, 2],
                "axes": {"arm": [{"name": "a", "overrides": ["eval.episodes=1"]}, {"name": "b", "seeds": [1]}]},
                "budgets": {"all": {"value_seeds": value_seeds}},
            }
        )

    planned = lambda s: [(r.axes["arm"], r.seed) for r in plan_runs(s, "/x", "all")]  # noqa: E731
    assert planned(spec({})) == [("a", 0), ("a", 1), ("a", 2), ("b", 1)]
    assert planned(spec({"arm": {"b": None}})) == [("a", 0), ("a", 1), ("a", 2), ("b", 0), ("b", 1), ("b", 2)]
    assert planned(spec({"arm": {"b": [0, 2], "a": [2]}})) == [("a", 2), ("b", 0), ("b", 2)]
    with pytest.raises(ValidationError, match=r"value_seeds names unknown axis 'arms'; axes: \['arm'\]"):
        spec({"arms": {"b": None}})
    with pytest.raises(
        ValidationError, match=r"value_seeds of axis 'arm' names no value\(s\) \['c'\]; values: \['a', 'b'\]"
    ):
        spec({"arm": {"c": None}})
    # table1 --budget decisive plans exactly the runs stage 2 is made of (the spec the queue ran, committed)
    decisive = plan_runs(load_experiment("table1"), "/x", "decisive")
    made = plan_runs(load_experiment(str(REPO / "docs/reports/issue34/table1_decisive.yaml")), "/x", "decisive")
    assert [(r.run_id, r.recipe, r.overrides) for r in decisive] == [(r.run_id, r.recipe, r.overrides) for r in made]
    assert sorted({r.axes["algorithm"] for r in decisive}) == ["adarl", "parseval"] and len(decisive) == 16


def test_a_budget_may_give_a_value_its_own_overrides():
    """``value_overrides``: a budget adds overrides to the runs of one axis value, after the value's and the budget's
    own (so they win), e.g. one env's Table 1 row runs Parseval at the lambda selected on that env; an unknown axis or
    value is refused, naming the known ones; the other values' runs are untouched."""
    from pydantic import ValidationError

    from adarl.experiments.spec import ExperimentSpec, plan_runs

    def spec(value_overrides):
        return ExperimentSpec.model_validate(
            {
                "kind": "experiment",
                "name": "x",
                "recipe": "quickstart",
                "seeds": [0],
                "axes": {
                    "env": ["e1", "e2"],
                    "arm": [
                        {"name": "a", "overrides": ["eval.episodes=1"]},
                        {"name": "b", "overrides": ["rank.beta=0.9"]},
                    ],
                },
                "budgets": {"all": {"overrides": ["eval.episodes=2"], "value_overrides": value_overrides}},
            }
        )

    def planned(s):
        return {r.run_id: r.overrides for r in plan_runs(s, "/x", "all")}

    plain = planned(spec({}))
    given = planned(spec({"arm": {"b": ["rank.beta=0.95", "eval.episodes=3"]}}))
    assert (
        given["env=e1__arm=a__seed=0"]
        == plain["env=e1__arm=a__seed=0"]
        == ["eval.episodes=1", "eval.episodes=2", "seed=0"]
    )
    assert given["env=e2__arm=b__seed=0"] == [
        "rank.beta=0.9",
        "eval.episodes=2",
        "rank.beta=0.95",
        "eval.episodes=3",
        "seed=0",
    ]
    with pytest.raises(ValidationError, match=r"value_overrides names unknown axis 'arms'; axes: \['env', 'arm'\]"):
        spec({"arms": {"b": []}})
    with pytest.raises(
        ValidationError, match=r"value_overrides of axis 'arm' names no value\(s\) \['c'\]; values: \['a', 'b'\]"
    ):
        spec({"arm": {"c": []}})


def test_table2s_budgets_run_the_arms_they_name():
    """A scope added to table2's axis (the follow-up's sac_full) must not join a budget that names no scope list:
    each laptop budget runs exactly the arms its description gives."""
    from adarl.experiments.spec import load_experiment, plan_runs

    spec = load_experiment("table2")

    def scopes(budget):
        return sorted({dict(r.axes)["scope"] for r in plan_runs(spec, "/x", budget)})

    assert scopes("laptop") == ["actor", "both", "critic"]
    assert scopes("laptop_dense_critic") == ["actor", "actor_dense_critic", "both", "critic"]
    assert scopes("laptop_dense") == ["sac_full"]
