"""`adarl tune` (issue 32): bad search spaces refused by name before anything is written; the pruner fed from a
trial's eval.csv; a small study on the linear CartPole killed mid-trial with kill -9 and started again, ending
with its trial count, no trial counted twice and the interrupted one resumed from its checkpoint."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

optuna = pytest.importorskip("optuna")

REPO = Path(__file__).resolve().parents[1]
TINY = [
    "collector.total_frames=600",
    "collector.init_random_frames=200",
    "collector.frames_per_batch=100",
    "algorithm.batch_size=32",
    "rank.interval=150",
    "replay.size=2000",
    "replay.warm_start.frames=100",
    "lr_schedule.warmup_steps=20",
    "eval.interval=300",
    "eval.episodes=2",
    "eval.max_steps=50",
    "checkpoint.interval=300",
]


def _spec(tmp_path: Path, **changes) -> Path:
    spec = {
        "kind": "tune",
        "name": "tiny",
        "recipe": "linear_cartpole_sac",
        "overrides": TINY,
        "space": {
            "rank.beta": {"type": "float", "low": 0.8, "high": 0.99},
            "algorithm.lr": {"type": "float", "low": 1.0e-4, "high": 3.0e-3, "log": True},
            "replay.warm_start.mode": {"type": "categorical", "choices": ["refill", "keep"]},
        },
        "objective": {"metric": "score", "score_last": 1},
        "n_trials": 2,
        "sampler": {"name": "random", "seed": 0},
        "pruner": {"name": "none"},
    }
    for key, value in changes.items():
        spec[key] = value
    path = tmp_path / "tune.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


BAD = {
    "unknown recipe key": (
        {"space": {"rank.bta": {"type": "float", "low": 0.8, "high": 0.9}}},
        ["space 'rank.bta'", "did you mean 'beta'"],
    ),
    "low above high": (
        {"space": {"rank.beta": {"type": "float", "low": 0.9, "high": 0.8}}},
        ["space.rank.beta", "low (0.9) > high (0.8)"],
    ),
    "log with low <= 0": (
        {"space": {"algorithm.lr": {"type": "float", "low": 0.0, "high": 0.01, "log": True}}},
        ["space.algorithm.lr", "log scale needs low > 0"],
    ),
    "an end the recipe refuses": (
        {"space": {"rank.beta": {"type": "float", "low": 0.5, "high": 1.5}}},
        ["space 'rank.beta' = 1.5", "rank.beta", "(0, 1)"],
    ),
    "a choice the recipe refuses": (
        {"space": {"replay.warm_start.mode": {"type": "categorical", "choices": ["refill", "refil"]}}},
        ["space 'replay.warm_start.mode' = 'refil'"],
    ),
    "bad sampler name": ({"sampler": {"name": "tpee"}}, ["sampler.name", "'tpe', 'random' or 'grid'"]),
    "misspelt spec key": ({"n_trails": 3}, ["n_trails", "did you mean 'n_trials'"]),
    "grid without a float step": (
        {"sampler": {"name": "grid"}},
        ["grid sampler needs a finite grid", "rank.beta"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_search_spaces_are_refused_by_name_before_anything_is_written(tmp_path, capsys, case):
    from adarl.cli import main

    changes, expected = BAD[case]
    out = tmp_path / "out"
    rc = main(["tune", str(_spec(tmp_path, **changes)), "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    for text in expected:
        assert text in err, (case, err)
    assert not out.exists()


def test_override_values_and_grids():
    from adarl.experiments.tune_spec import Param, grid_values, override_value

    assert [override_value(v) for v in (1e-05, 0.5, 3, True, None, "keep")] == [
        "1.0e-05",
        "0.5",
        "3",
        "true",
        "null",
        "keep",
    ]
    assert grid_values(Param(type="int", low=500, high=2000, step=500)) == [500, 1000, 1500, 2000]
    assert grid_values(Param(type="float", low=0.1, high=0.3, step=0.1)) == pytest.approx([0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="multiple of step"):
        Param(type="int", low=0, high=10, step=3)


def test_the_pruner_reads_the_trials_evaluations(tmp_path):
    """What the watcher does while a trial trains: report each new line of eval.csv once, then ask the pruner."""
    from adarl.experiments.tune import _Study
    from adarl.experiments.tune_spec import load_tune_spec

    spec = load_tune_spec(_spec(tmp_path, pruner={"name": "median", "n_startup_trials": 1}))
    out = tmp_path / "out"
    out.mkdir()
    driver = _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)
    good = driver.study.ask(driver.dists)
    for step, value in ((300, 50.0), (600, 60.0)):
        good.report(value, step)
    driver.study.tell(good, 60.0)
    run = out / "trials" / "trial-0001"
    run.mkdir(parents=True)
    rows = 'frames,updates,mean,std,ci95,episodes,returns,ranks\n300,10,5.0,0,0,2,"[5, 5]",{}\n600,20,4.'
    (run / "eval.csv").write_text(rows)  # the second line is being written: not read yet
    bad = driver.study.ask(driver.dists)
    assert driver._report(bad, run) is True
    assert driver._report(bad, run) is True  # reported once
    assert driver.storage.get_trial(bad._trial_id).intermediate_values == {300: 5.0}


def _checkpoint_frames(run: Path) -> list[int]:
    return [int(p.stem.split("-")[1]) for p in (run / "checkpoints").glob("ckpt-*.pt")]


@pytest.mark.slow
def test_a_study_killed_mid_trial_continues_with_its_trial_count_and_no_duplicate(tmp_path):
    spec = _spec(tmp_path)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "adarl.cli", "tune", str(spec), "-o", str(out)],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    second = out / "trials" / "trial-0001"
    deadline = time.monotonic() + 600  # a guard against a hang, not a timing window: we wait for the file
    while not (second.is_dir() and any(f > 0 for f in _checkpoint_frames(second))):
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    holder = json.loads((second / ".adarl.lock").read_text())["pid"]
    while True:  # the trial's trainer dies with its parent (PR_SET_PDEATHSIG); wait until it is gone
        try:
            os.kill(holder, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline
        time.sleep(0.05)

    storage = f"sqlite:///{out / 'study.db'}"
    before = optuna.load_study(study_name="tiny", storage=storage).trials
    assert [(t.number, t.state.name) for t in before] == [(0, "COMPLETE"), (1, "RUNNING")]

    from adarl.experiments.execute import read_attempts
    from adarl.experiments.tune import run_tune
    from adarl.runtime.config import load_recipe

    said: list[str] = []
    result = run_tune(spec, output=out, log=said.append)
    assert "1 of 2 trials done, 1 interrupted to resume" in said[0]
    assert result.states == {"COMPLETE": 2} and result.resumed == [1]
    after = optuna.load_study(study_name="tiny", storage=storage).trials
    assert [t.number for t in after] == [0, 1]
    assert [t.params for t in after] == [t.params for t in before]  # same trial, same parameters
    assert sorted(p.name for p in (out / "trials").glob("trial-*") if p.is_dir()) == ["trial-0000", "trial-0001"]
    assert [a["action"] for a in read_attempts(out / "trials", "trial-0001") if a["event"] == "start"] == [
        "ran",
        "resumed",
    ]
    # the result: the best trial's recipe, the table and the report
    with (out / "trials.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["state"] for r in rows] == ["COMPLETE", "COMPLETE"]
    values = [float(r["value"]) for r in rows]
    best = max(range(2), key=values.__getitem__)
    assert result.best_value == values[best]
    recipe = load_recipe(str(out / "best_recipe.yaml"))
    assert recipe.rank.beta == pytest.approx(after[best].params["rank.beta"])
    assert recipe.replay.warm_start.mode == after[best].params["replay.warm_start.mode"]
    assert json.loads((out / "trials" / f"trial-{best:04d}" / "tune_trial.json").read_text())["state"] == "COMPLETE"
    report = (out / "report.md").read_text()
    assert f"**Best: trial {best}" in report and "![optimisation history](optimization_history.png)" in report
    assert (out / "optimization_history.png").is_file()
    # a third start has nothing left to do
    again = run_tune(spec, output=out, log=said.append)
    assert again.states == {"COMPLETE": 2} and again.resumed == []


def test_the_shipped_tune_specs_validate_and_are_not_recipes():
    from adarl.experiments.tune_spec import check_space, load_tune_spec
    from adarl.runtime.config import list_recipes

    specs = sorted((REPO / "recipes" / "tune").glob("*.yaml"))
    assert [p.stem for p in specs] == ["cartpole_beta"]
    assert not any(name.startswith("tune/") for name, _ in list_recipes())
    for p in specs:
        assert check_space(load_tune_spec(p.stem)) > 0


def test_grid_sampler_and_the_sweep_objective(tmp_path):
    """The grid covers its points once each (the budget capped at its size, no study.stop() outside optimize);
    the sweep objective reads the worst case of the trial's sweep."""
    from adarl.experiments.tune import _grid_size, _Study
    from adarl.experiments.tune_spec import load_tune_spec

    space = {
        "rank.beta": {"type": "float", "low": 0.8, "high": 0.9, "step": 0.1},
        "replay.warm_start.mode": {"type": "categorical", "choices": ["refill", "keep"]},
    }
    sweep = {"params": ["pole_length=0.4,0.6"], "episodes": 1, "name": "pole"}
    spec = load_tune_spec(
        _spec(
            tmp_path,
            space=space,
            sampler={"name": "grid"},
            objective={"metric": "sweep_worst", "sweep": sweep, "worst": "worst_case"},
        )
    )
    assert _grid_size(spec.space) == 4
    out = tmp_path / "out"
    out.mkdir()
    driver = _Study(spec, out, 4, 1, log=lambda *_: None)
    seen = []
    for _ in range(4):
        trial = driver.study.ask(driver.dists)
        seen.append((round(trial.params["rank.beta"], 6), trial.params["replay.warm_start.mode"]))
        driver.study.tell(trial, 1.0)
    assert sorted(seen) == [(0.8, "keep"), (0.8, "refill"), (0.9, "keep"), (0.9, "refill")]
    run = tmp_path / "run"
    (run / "sweeps").mkdir(parents=True)
    (run / "sweeps" / "pole.json").write_text(json.dumps({"worst_mean": 12.5, "worst_case": 3.0}))
    assert driver._objective(run) == 3.0


def test_a_study_folder_refuses_another_search_space(tmp_path):
    from adarl.errors import RecipeError
    from adarl.experiments.tune import _Study
    from adarl.experiments.tune_spec import load_tune_spec

    out = tmp_path / "out"
    out.mkdir()
    spec = load_tune_spec(_spec(tmp_path))
    _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)
    _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)  # the same spec continues it
    other = load_tune_spec(_spec(tmp_path, space={"rank.beta": {"type": "float", "low": 0.5, "high": 0.9}}))
    with pytest.raises(RecipeError, match="made with another space"):
        _Study(other, out, other.n_trials, 1, log=lambda *_: None)
    flipped = load_tune_spec(_spec(tmp_path, direction="minimize"))
    with pytest.raises(RecipeError, match="direction"):
        _Study(flipped, out, flipped.n_trials, 1, log=lambda *_: None)
