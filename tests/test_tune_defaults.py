"""Tuning as rl-zoo users know it (issue 48.3): default search spaces per algorithm (and the rank rule's),
`adarl tune RECIPE`, tune and experiment specs listed by `adarl recipes` and found by name in an installed layout,
a shipped tune spec per paper env; and (48.6) a trial's recorded last_step/evaluations are those its value used."""

from __future__ import annotations

import csv
import shutil

import pytest
import yaml
from _helpers import REPO, tiny

optuna = pytest.importorskip("optuna")


def _keys(spec) -> set[str]:
    return set(spec.space)


def test_default_spaces_per_algorithm_and_rank_rule():
    from adarl.errors import RecipeError
    from adarl.experiments.tune import RANK_KEYS, check_space, tune_target

    sac = tune_target("hopper_adarl")
    assert _keys(sac) == {
        "algorithm.gamma",
        "algorithm.lr",
        "algorithm.batch_size",
        "algorithm.tau",
        "replay.size",
        *RANK_KEYS,
    }
    assert sac.space["algorithm.tau"].choices == [0.001, 0.005, 0.01, 0.02, 0.05, 0.08]  # rl-zoo's, as they are
    assert (sac.space["algorithm.lr"].low, sac.space["algorithm.lr"].high) == (1e-5, 1e-2)  # rl-zoo: up to 1
    interval = sac.space["rank.interval"]  # an eighth to a half of the budget's updates (3.5e6 frames)
    assert (interval.low, interval.high, interval.log) == (437_500, 1_750_000, True)
    assert (sac.n_trials, sac.sampler.name, sac.pruner.name, sac.pruner.n_warmup_steps) == (
        20,
        "tpe",
        "median",
        3.5e6 // 3,
    )
    td3 = tune_target("baselines/hopper_td3", n_trials=3)
    assert _keys(td3) == _keys(sac) | {"algorithm.td3.exploration_noise"} and td3.n_trials == 3
    assert td3.name == "baselines-hopper_td3"
    assert _keys(tune_target("baselines/hopper_ddpg")) == _keys(td3)
    ppo = tune_target("baselines/ppo_base", ["collector.frames_per_batch=128"])
    assert not _keys(ppo) & set(RANK_KEYS)  # PPO runs without rank adaptation
    assert "algorithm.ppo.clip_epsilon" in _keys(ppo) and "algorithm.ppo.gae_lambda" in _keys(ppo)
    assert ppo.space["algorithm.ppo.minibatch_size"].choices == [32, 64, 128]  # <= the collector's batch
    # the rank rule's keys follow what the recipe reads; keys the overrides set are left out of the space
    fixed = tune_target("hopper_adarl", ["rank.rule=fixed", "rank.target_rank=8", "algorithm.lr=1e-3"])
    assert "rank.beta" not in _keys(fixed) and "rank.accept.actor_tol" not in _keys(fixed)
    assert "algorithm.lr" not in _keys(fixed) and "rank.interval" in _keys(fixed)
    plain = tune_target("hopper_adarl", ["rank.enabled=false"])
    assert not _keys(plain) & set(RANK_KEYS)
    # an algorithm on SAC's loop without a table of its own: a key one of its options sets is searched as that
    # option, a key its loop refuses for it (CrossQ has no target network: tau) is left out
    crossq = tune_target("baselines/hopper_crossq")
    assert "algorithm.options.lr" in _keys(crossq) and not {"algorithm.lr", "algorithm.tau"} & _keys(crossq)
    assert {"algorithm.lr", "algorithm.tau"} <= _keys(tune_target("baselines/hopper_tqc"))
    for spec in (td3, ppo, crossq):  # sac's: every shipped spec (the next test)
        assert check_space(spec) > 0  # each end of each default range is a value the recipe accepts
    every = [f"{k}=1" for k in ("algorithm.gamma", "algorithm.lr", "algorithm.batch_size", "algorithm.tau")]
    with pytest.raises(RecipeError, match="default search space .* is empty: the overrides set every key"):
        tune_target("hopper_adarl", [*every, "replay.size=1000", "rank.enabled=false"])
    with pytest.raises(RecipeError, match=r"no tune spec or recipe named 'hoper_adarl'; did you mean 'hopper_adarl'"):
        tune_target("hoper_adarl")
    with pytest.raises(RecipeError, match=r"'table1' is an experiment spec.*adarl experiment table1"):
        tune_target("table1")
    # an explicit space: an override of one of its keys would never train (each trial sets it after the overrides)
    with pytest.raises(RecipeError, match=r"override 'rank.beta=0.9' sets a key of the search space"):
        tune_target("cartpole_beta", ["rank.beta=0.9"])
    assert tune_target("cartpole_beta", ["collector.total_frames=3000"], n_trials=2).overrides[-1] == (
        "collector.total_frames=3000"
    )


def test_shipped_specs_validate_list_and_resolve_by_name_when_installed(tmp_path, monkeypatch, capsys):
    import adarl.cli as cli
    from adarl.experiments.spec import load_experiment
    from adarl.experiments.tune import DESCRIPTION, check_space, load_tune_spec, shipped_tune_specs
    from adarl.runtime.config import discovery

    names = shipped_tune_specs()
    for env in ("hopper", "walker2d", "ant", "humanoid", "cartpole"):
        assert f"{env}_tune" in names
    for name in names:
        spec = load_tune_spec(name)
        assert check_space(spec) > 0 and spec.space, name
    # an installed wheel: the recipes are the package data adarl/recipes/ (no source tree's recipes/)
    installed = tmp_path / "site" / "adarl" / "recipes"
    shutil.copytree(REPO / "recipes", installed)
    monkeypatch.setattr(discovery, "_package_recipes_dir", lambda: installed)
    monkeypatch.chdir(tmp_path)
    spec = load_tune_spec("hopper_tune")
    assert spec.recipe == "hopper_adarl" and spec.overrides[0] == "collector.total_frames=200000"
    assert load_experiment("table1").name == "table1"
    assert cli.main(["recipes"]) == 0
    out = capsys.readouterr().out
    recipes, rest = out.split("\nexperiment specs (adarl experiment NAME):\n")
    experiments, tunes = rest.split("\ntune specs (adarl tune NAME")
    assert "hopper_adarl " in recipes and "tune/" not in recipes and "table1 " not in recipes
    assert "table1 " in experiments and "hopper_tune " in tunes and "cartpole_beta " in tunes
    assert "adarl recipes" in DESCRIPTION and "recipes/tune" not in DESCRIPTION
    assert "adarl recipes" in " ".join(
        cli.build_parser()._subparsers._group_actions[0].choices["experiment"].description.split()
    )


@pytest.mark.slow
def test_tune_a_recipe_over_its_default_space_records_the_evaluations_its_value_used(tmp_path, capsys):
    """`adarl tune RECIPE overrides --n-trials 1`: the default space less the keys the overrides pin, written to
    tune_spec.yaml; each trial's last_step / evaluations (trials.csv, report) are those of its eval.csv, the final
    evaluation included (before: the one at the end of training was never reported)."""
    import adarl.cli as cli

    out = tmp_path / "study"
    overrides = tiny("collector.total_frames=500", "eval.interval=250", "checkpoint.interval=250")
    assert cli.main(["tune", "linear_cartpole_sac", *overrides, "--n-trials", "1", "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "space: the default space of sac + the rank rule's (6 keys); set by the overrides" in said
    run = yaml.safe_load((out / "tune_spec.yaml").read_text())
    assert (out / "tune_spec.yaml").read_text().startswith("# space: the default space of sac")
    assert set(run["space"]) == {
        "algorithm.gamma",
        "algorithm.lr",
        "algorithm.tau",
        "rank.beta",
        "rank.accept.actor_tol",
        "rank.accept.critic_tol",
    }  # batch_size, replay.size and rank.interval are pinned by the tiny overrides
    assert run["overrides"] == overrides and run["n_trials"] == 1
    rows = list(csv.DictReader((out / "trials.csv").open()))
    assert [r["state"] for r in rows] == ["COMPLETE"]
    report = (out / "report.md").read_text()
    for row in rows:
        evals = list(csv.DictReader((out / row["run_dir"] / "eval.csv").open()))
        frames = [int(e["frames"]) for e in evals]
        assert frames[-1] >= 500 and len(frames) >= 2
        assert (int(row["last_step"]), int(row["evaluations"])) == (frames[-1], len(frames)), (row, frames)
        value = sum(float(e["mean"]) for e in evals[-1:]) / 1  # score_last 1 (the spec's default)
        assert float(row["value"]) == pytest.approx(value)
        line = next(ln for ln in report.splitlines() if ln.startswith(f"| {row['number']} | complete |"))
        assert line.rstrip(" |").endswith(str(frames[-1]))


def test_a_trial_records_the_evaluations_its_value_used(tmp_path):
    """Issue 48.6: the evaluation at the end of training lands after the watcher's last poll (the run exits within
    its poll interval); the trial's value used it, so it is reported before the value is told: trials.csv and the
    report say last_step 600, evaluations 3 (before: 500 and 2, of a value that included 600)."""
    from adarl.experiments.tune import load_tune_spec, trial_dir
    from adarl.experiments.tune._outputs import write_outputs
    from adarl.experiments.tune._study import _Study

    path = tmp_path / "spec.yaml"
    spec = {"kind": "tune", "name": "t", "recipe": "linear_cartpole_sac", "overrides": tiny(), "n_trials": 1}
    spec |= {"space": "default", "objective": {"metric": "score", "score_last": 2}, "pruner": {"name": "none"}}
    path.write_text(yaml.safe_dump(spec))
    spec = load_tune_spec(path)
    out = tmp_path / "out"
    out.mkdir()
    driver = _Study(spec, out, 1, 1, log=lambda *_: None)
    trial = driver.study.ask(driver.dists)
    run = trial_dir(out, 0)
    run.mkdir(parents=True)
    head = "frames,updates,mean,std,ci95,episodes,returns,ranks\n"
    seen = '250,50,10.0,0,0,2,"[10, 10]",{}\n500,300,20.0,0,0,2,"[20, 20]",{}\n'
    (run / "eval.csv").write_text(head + seen)
    assert driver._report(trial, [run]) is False  # the watcher's last poll: 250 and 500
    (run / "eval.csv").write_text(head + seen + '600,400,40.0,0,0,2,"[40, 40]",{}\n')  # then the run's end
    runs = driver._planned(0, dict(trial.params))
    runs[0].status = "finished"
    driver._finish(trial, runs, run, dict(trial.params), None)
    done = driver.study.trials[0]
    assert (done.state.name, done.value) == ("COMPLETE", 30.0)  # the mean of the last two: 20 and 40
    assert done.intermediate_values == {250: 10.0, 500: 15.0, 600: 30.0}  # what it reports is what its value is
    write_outputs(driver.study, spec, out, log=lambda *_: None)
    row = next(csv.DictReader((out / "trials.csv").open()))
    assert (row["last_step"], row["evaluations"], row["value"]) == ("600", "3", "30.0")
    assert "| 0 | complete | 30 |" in (out / "report.md").read_text()
    assert (out / "report.md").read_text().split("| 0 | complete | 30 |")[1].split("\n")[0].endswith(" 600 |")
