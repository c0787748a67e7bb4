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
from _helpers import tiny

optuna = pytest.importorskip("optuna")

REPO = Path(__file__).resolve().parents[1]
TINY = tiny()


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
    "seed and seeds": ({"seed": 1, "seeds": [0, 1]}, ["give `seed`", "or `seeds`", "not both"]),
    "repeated seeds": ({"seeds": [0, 1, 0]}, ["seeds must be distinct, got [0, 1, 0]"]),
    "no seeds": ({"seeds": []}, ["`seeds` needs at least one seed"]),
    "grid without a float step": (
        {"sampler": {"name": "grid"}},
        ["grid sampler needs a finite grid", "rank.beta"],
    ),
    # issue 46.4: each trial sets its own seed (and output) after the space's point: a space or override setting
    # them was recorded as the trial's parameter while the run trained with the trial's seed
    "seed in the space": (
        {"space": {"seed": {"type": "int", "low": 0, "high": 100}}},
        ["space 'seed'", "each trial sets it itself", "seeds"],
    ),
    "seed in the overrides": ({"overrides": [*TINY, "seed=3"]}, ["override 'seed=3'", "each trial sets it itself"]),
    "an output key in the space": (
        {"space": {"output.dir": {"type": "categorical", "choices": ["a", "b"]}}},
        ["space 'output.dir'", "each trial sets it itself"],
    ),
    "a name that is no folder name": ({"name": ".."}, ["name", "'..'"]),  # issue 46.5: it wrote into runs/
    # issue 48.3: `space: default` (or none) is the default space; an empty one or another word is refused
    "an empty space": ({"space": {}}, ["space is empty", "or `default`"]),
    "a space that is a word": ({"space": "defualt"}, ["space must be a mapping of recipe keys, or `default`"]),
    "an override of a space key": (
        {"overrides": [*TINY, "rank.beta=0.9"]},
        ["override 'rank.beta=0.9' sets a key of the search space"],
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
    from adarl.experiments.tune import Param, grid_values, override_value

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
    from adarl.experiments.tune import load_tune_spec
    from adarl.experiments.tune._study import _Study

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
    assert driver._report(bad, [run]) is True
    assert driver._report(bad, [run]) is True  # reported once
    assert driver.storage.get_trial(bad._trial_id).intermediate_values == {300: 5.0}


def test_a_watched_run_holds_after_an_evaluation_until_its_watcher_read_it(tmp_path, capsys, monkeypatch):
    """The trainer's side of the pruning handshake (adarl.runtime.run_folder.verdicts): no watcher's file, no wait;
    a verdict on that evaluation or a later one, or a stop asked, releases it; a file left unchanged for STALE_S
    (measured by the run's own clock, never against the watcher's) releases it with a word (the handshake never hangs
    a run whose study died)."""
    from adarl.runtime.run_folder import verdicts

    run = tmp_path / "trials" / "trial-0000" / "seed=1"
    never = lambda: False  # noqa: E731
    assert verdicts.await_verdict(run, 300, never) == "unwatched"
    watcher = verdicts.Watcher(run)
    watcher.start()  # before the run's folder exists: a trial's seeds' runs make theirs later
    assert json.loads(verdicts.watch_file(run).read_text())["seen"] == -1
    assert verdicts.await_verdict(run, 300, lambda: True) == "stopping"
    watcher.seen(600)
    assert verdicts.await_verdict(run, 300, never) == "seen" and verdicts.await_verdict(run, 600, never) == "seen"
    monkeypatch.setattr(verdicts, "STALE_S", 0.3)  # the file left unchanged (its watcher gone) this long, by our clock
    assert verdicts.await_verdict(run, 900, never) == "stale"
    said = capsys.readouterr().err
    assert "has not answered for 0.3 s: training on without its verdict on the evaluation at 900 frames" in said
    watcher.close()
    assert not verdicts.watch_file(run).exists() and verdicts.await_verdict(run, 900, never) == "unwatched"


@pytest.mark.slow
def test_a_trial_is_pruned_at_the_first_evaluation_past_the_warm_up_however_slow_its_watcher(tmp_path, monkeypatch):
    """The CI failure of 2026-11-28: a short trial trained past the evaluation that prunes it before the watcher's
    next poll, and ended COMPLETE. Each evaluation now waits for the watcher's verdict, so a watcher polling every
    3 s (slower than a few batches train: without the wait it pruned at 700 or later) prunes it at 500 frames, the
    first evaluation at or past the warm-up, and its run checkpoints there and stops, resumable."""
    from adarl.experiments import execute
    from adarl.experiments.tune import run_tune
    from adarl.runtime.run_folder.verdicts import watch_file

    monkeypatch.setattr(execute, "WATCH_POLL_S", 3.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("PYTHONPATH", str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    pruner = {"name": "median", "n_startup_trials": 1, "n_warmup_steps": 500}
    spec = _spec(tmp_path, overrides=[*TINY, "collector.total_frames=3000", "eval.interval=100"], pruner=pruner)
    out = tmp_path / "out"
    _add_unbeatable_trial(spec, out)
    said: list[str] = []
    result = run_tune(spec, output=out, log=said.append)
    assert result.states == {"COMPLETE": 1, "PRUNED": 1}, said
    _assert_pruned_and_checkpointed(out, 1, 500)
    trial = out / "trials" / "trial-0001"
    assert json.loads((trial / "tune_trial.json").read_text())["pruned_at_frames"] == 500
    with (trial / "eval.csv").open() as fh:
        assert [int(r["frames"]) for r in csv.DictReader(fh)] == [100, 200, 300, 400, 500]  # held until each verdict
    assert not watch_file(trial).exists()  # the watcher's file goes with its trial


def _checkpoint_frames(run: Path) -> list[int]:
    return [int(p.stem.split("-")[1]) for p in (run / "checkpoints").glob("ckpt-*.pt")]


def _kill_9_mid_trial(spec: Path, out: Path, trial: Path, *args: str) -> None:
    """``adarl tune SPEC -o OUT ARGS`` in a subprocess, killed with kill -9 once ``trial`` has a checkpoint past
    frame 0; returns once the trial's trainer is gone too (it dies with its parent, or with the Ray it started)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "adarl.cli", "tune", str(spec), "-o", str(out), *args],
        cwd=REPO,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 600  # a guard against a hang, not a timing window: we wait for the file
    while not (trial.is_dir() and any(f > 0 for f in _checkpoint_frames(trial))):
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    holder = json.loads((trial / ".adarl.lock").read_text())["pid"]
    # the trainer is frozen where its checkpoint was seen: a Ray worker outlives its killed driver for seconds,
    # and its trainer would train on meanwhile (to an evaluation that prunes the trial before it resumes)
    os.kill(holder, signal.SIGSTOP)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    while True:  # the trial's trainer dies with its parent (PR_SET_PDEATHSIG); wait until it is gone
        try:
            os.kill(holder, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline
        time.sleep(0.05)


@pytest.mark.slow
def test_a_study_killed_mid_trial_continues_with_its_trial_count_and_no_duplicate(tmp_path):
    spec = _spec(tmp_path)
    out = tmp_path / "out"
    _kill_9_mid_trial(spec, out, out / "trials" / "trial-0001")

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
    from adarl.experiments.tune import check_space, load_tune_spec
    from adarl.runtime.config import list_recipes

    specs = sorted((REPO / "recipes" / "tune").glob("*.yaml"))
    assert [p.stem for p in specs] == [
        "ant_tune",
        "cartpole_beta",
        "cartpole_tune",
        "hopper_tune",
        "humanoid_tune",
        "walker2d_tune",
    ]  # one per paper env (tests/test_tune_defaults.py), and the rank knobs on the linear CartPole
    assert not any(name.startswith("tune/") for name, _ in list_recipes())
    for p in specs:
        assert check_space(load_tune_spec(p.stem)) > 0


def test_grid_sampler_and_the_sweep_objective(tmp_path):
    """The grid covers its points once each (the budget capped at its size, no study.stop() outside optimize);
    the sweep objective reads the worst case of the trial's sweep."""
    from adarl.experiments.tune import load_tune_spec
    from adarl.experiments.tune._study import _grid_size, _Study

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
    from adarl.experiments.tune import load_tune_spec
    from adarl.experiments.tune._study import _Study

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
    _Study(load_tune_spec(_spec(tmp_path, seeds=[0])), out, 2, 1, log=lambda *_: None)  # seeds [0] is seed 0
    seeds = load_tune_spec(_spec(tmp_path, seeds=[0, 1]))
    with pytest.raises(RecipeError, match=r"another seeds \(\[0\] in the study, \[0, 1\] in the spec\)"):
        _Study(seeds, out, seeds.n_trials, 1, log=lambda *_: None)


def test_a_study_made_before_seeds_existed_continues_with_its_seed(tmp_path):
    """Studies recorded `seed` (an int) before `seeds` existed: the same seed continues them, another is refused."""
    from adarl.errors import RecipeError
    from adarl.experiments.tune import STUDY_FILE, load_tune_spec
    from adarl.experiments.tune._study import _Study

    out = tmp_path / "out"
    out.mkdir()
    spec = load_tune_spec(_spec(tmp_path))
    old = optuna.create_study(study_name="tiny", storage=f"sqlite:///{out / STUDY_FILE}", direction="maximize")
    made = {
        "space": {k: p.model_dump() for k, p in spec.space.items()},
        "recipe": spec.recipe,
        "overrides": list(spec.overrides),
        "seed": 0,
        "objective": spec.objective.model_dump(),
        "direction": spec.direction,
    }
    for key, value in json.loads(json.dumps(made)).items():
        old.set_user_attr(key, value)
    _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)
    other = load_tune_spec(_spec(tmp_path, seed=3))
    with pytest.raises(RecipeError, match=r"another seeds \(\[0\] in the study, \[3\] in the spec\)"):
        _Study(other, out, other.n_trials, 1, log=lambda *_: None)


def test_what_the_pruner_sees_of_several_seeds(tmp_path):
    """The mean over seeds at each frame count that every seed reached, each seed at its last evaluation by then;
    a frame count some seed has not reached yet waits."""
    from adarl.experiments.tune import load_tune_spec, mean_scores
    from adarl.experiments.tune._study import _Study

    a, b = [(300, 10.0), (600, 20.0), (900, 40.0)], [(400, 30.0), (700, 50.0)]
    assert mean_scores([a, b]) == [(400, 20.0), (600, 25.0), (700, 35.0)]  # 300: b not evaluated; 900: b not there
    assert mean_scores([a, []]) == []
    assert mean_scores([a]) == a

    spec = load_tune_spec(_spec(tmp_path, seeds=[0, 1], pruner={"name": "none"}))
    out = tmp_path / "out"
    out.mkdir()
    driver = _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)
    trial = driver.study.ask(driver.dists)
    paths = [Path(r.path) for r in driver._planned(trial.number, trial.params)]
    assert [p.relative_to(out).as_posix() for p in paths] == ["trials/trial-0000/seed=0", "trials/trial-0000/seed=1"]
    assert [r.overrides[-1] for r in driver._planned(trial.number, trial.params)] == ["seed=0", "seed=1"]
    head = "frames,updates,mean,std,ci95,episodes,returns,ranks\n"
    for path, rows in zip(paths, (["300,1,10.0", "600,2,20.0"], ["300,1,30.0"])):
        path.mkdir(parents=True)
        (path / "eval.csv").write_text(head + "".join(f'{r},0,0,2,"[1, 1]",{{}}\n' for r in rows))
    assert driver._report(trial, paths) is False
    assert driver.storage.get_trial(trial._trial_id).intermediate_values == {300: 20.0}


def _eval_means(run: Path) -> dict[int, float]:
    with (run / "eval.csv").open() as fh:
        return {int(r["frames"]): float(r["mean"]) for r in csv.DictReader(fh)}


@pytest.mark.slow
def test_a_study_with_two_seeds_per_trial(tmp_path, monkeypatch, capsys):
    """A trial of two seeds: a run folder per seed under the trial's folder, each seed's value recorded,
    the trial's value their mean, and what the pruner saw the mean over seeds at each frame count."""
    from adarl.cli import main
    from adarl.experiments.tune import run_tune

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    space = {  # keep mode: both seeds evaluate at the same frame counts
        "rank.beta": {"type": "float", "low": 0.8, "high": 0.99},
        "algorithm.lr": {"type": "float", "low": 1.0e-4, "high": 3.0e-3, "log": True},
    }
    overrides = [*TINY, "collector.total_frames=400", "eval.interval=200", "checkpoint.interval=400"]
    spec = _spec(tmp_path, seeds=[0, 1], space=space, overrides=overrides, n_trials=1)  # one trial: four runs' cost
    out = tmp_path / "out"
    said: list[str] = []
    result = run_tune(spec, output=out, log=said.append)
    assert result.states == {"COMPLETE": 1}, said
    trials = optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}").trials
    with (out / "trials.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    for t, row in zip(trials, rows):
        folder = out / "trials" / f"trial-{t.number:04d}"
        assert sorted(p.name for p in folder.iterdir() if p.name.startswith("seed=") and p.is_dir()) == [
            "seed=0",
            "seed=1",
        ]
        evals = [_eval_means(folder / f"seed={s}") for s in (0, 1)]
        assert list(evals[0]) == list(evals[1]) == [200, 400]
        seed_values = {str(s): evals[s][400] for s in (0, 1)}  # score_last 1: the last evaluation
        assert t.user_attrs["seed_values"] == pytest.approx(seed_values)
        assert t.value == pytest.approx((seed_values["0"] + seed_values["1"]) / 2)
        assert t.intermediate_values == pytest.approx({f: (evals[0][f] + evals[1][f]) / 2 for f in (200, 400)})
        assert float(row["value"]) == pytest.approx(t.value)
        assert [float(row["value_seed_0"]), float(row["value_seed_1"])] == pytest.approx(list(seed_values.values()))
        assert row["run_dir"] == f"trials/trial-{t.number:04d}"
        marker = json.loads((folder / "tune_trial.json").read_text())
        assert marker["state"] == "COMPLETE" and marker["seed_values"] == pytest.approx(seed_values)
    assert "seeds 0, 1 (a run each)" in (out / "report.md").read_text()
    assert yaml.safe_load((out / "tune_spec.yaml").read_text())["seeds"] == [0, 1]
    # the same folder with other seeds is refused by name, before anything runs
    other = _spec(tmp_path, seeds=[0, 2], space=space, overrides=overrides, n_trials=1)
    assert main(["tune", str(other), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "another seeds ([0, 1] in the study, [0, 2] in the spec)" in err and err.count("\n") == 1, err


def test_a_missing_launcher_extra_is_bad_input_and_writes_nothing(tmp_path, monkeypatch, capsys):
    import importlib.util

    from adarl.cli import main

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name in ("ray", "submitit") else real(name, *a)
    )
    for name in ("ray", "submitit"):  # `import ray` fails too, as where it is not installed
        monkeypatch.setitem(sys.modules, name, None)
    for launcher, extra in (("ray", "ray"), ("submitit", "slurm")):
        out = tmp_path / launcher
        assert main(["tune", str(_spec(tmp_path)), "-o", str(out), "--launcher", launcher]) == 2
        err = capsys.readouterr().err
        assert f"pip install 'adarl[{extra}]'" in err and err.count("\n") == 1, err
        assert not out.exists()


def _add_unbeatable_trial(spec_path: Path, out: Path) -> None:
    """Trial 0: a complete trial that no run of a few hundred frames can match at any frame count, so that the
    median pruner (n_startup_trials 1) prunes the next trial at its first evaluation past the warm-up."""
    from adarl.experiments.tune import load_tune_spec
    from adarl.experiments.tune._study import _Study

    spec = load_tune_spec(spec_path)
    out.mkdir()
    driver = _Study(spec, out, spec.n_trials, 1, log=lambda *_: None)
    params = {k: p.choices[0] if p.type == "categorical" else p.low for k, p in spec.space.items()}
    best = {frames: 1.0e6 for frames in range(0, 5001, 50)}
    driver.study.add_trial(
        optuna.trial.create_trial(params=params, distributions=driver.dists, value=1.0e6, intermediate_values=best)
    )


def _assert_pruned_and_checkpointed(out: Path, number: int, warmup: int) -> None:
    """The trial was stopped by its watcher, checkpointed past the frame count it was pruned at, and is resumable."""
    from adarl.experiments.execute import read_attempts, run_is_finished, stop_file

    run = out / "trials" / f"trial-{number:04d}"
    marker = json.loads((run / "tune_trial.json").read_text())
    assert marker["state"] == "PRUNED" and marker["pruned_at_frames"] >= warmup, marker
    ends = [a for a in read_attempts(out / "trials", run.name) if a["event"] == "end"]
    assert ends[-1]["status"] == "stopped", ends
    assert max(_checkpoint_frames(run)) >= marker["pruned_at_frames"]
    assert not run_is_finished(run) and not stop_file(run).exists()


@pytest.mark.slow
def test_a_study_on_ray_prunes_and_continues_after_kill_9(tmp_path):
    """Trials as Ray tasks: `adarl tune --launcher ray` killed with kill -9 mid-trial, started again: the trial is
    re-attached and resumed from its checkpoint on Ray, then pruned (stopped through its folder: it checkpoints)."""
    pytest.importorskip("ray")
    from adarl.experiments.execute import read_attempts
    from adarl.experiments.tune import run_tune
    from adarl.experiments.tune._records import scores

    pruner = {"name": "median", "n_startup_trials": 1, "n_warmup_steps": 500}
    spec = _spec(tmp_path, overrides=[*TINY, "collector.total_frames=900"], pruner=pruner)
    out = tmp_path / "out"
    _add_unbeatable_trial(spec, out)
    trial = out / "trials" / "trial-0001"
    _kill_9_mid_trial(spec, out, trial, "--launcher", "ray")  # the Ray it started goes too, and the training
    storage = f"sqlite:///{out / 'study.db'}"
    before = optuna.load_study(study_name="tiny", storage=storage).trials
    assert [(t.number, t.state.name) for t in before] == [(0, "COMPLETE"), (1, "RUNNING")]
    seen = [frames for frames, _ in scores(trial, 1)]  # the evaluations its first attempt wrote

    said: list[str] = []
    result = run_tune(spec, output=out, launcher="ray", log=said.append)
    assert "1 of 2 trials done, 1 interrupted to resume" in said[0] and "(runs on ray)" in said[0]
    assert result.states == {"COMPLETE": 1, "PRUNED": 1} and result.resumed == [1], said
    after = optuna.load_study(study_name="tiny", storage=storage).trials
    assert [t.number for t in after] == [0, 1] and after[1].params == before[1].params
    starts = [a["action"] for a in read_attempts(out / "trials", trial.name) if a["event"] == "start"]
    if max(seen, default=0) < 500:  # the trainer is frozen at its first checkpoint (300 frames): the usual case
        assert starts == ["ran", "resumed"]
        _assert_pruned_and_checkpointed(out, 1, 500)
    else:  # its first attempt's evaluations already prune it: pruned there, not trained again
        assert starts == ["ran"]
        marker = json.loads((trial / "tune_trial.json").read_text())
        assert marker["state"] == "PRUNED" and marker["pruned_at_frames"] == max(seen), marker


@pytest.mark.slow
def test_a_study_on_submitit_prunes_a_trial_so_that_it_checkpoints(tmp_path, monkeypatch):
    """Trials as submitit jobs (its local executor): a pruned trial's job stops its run, which checkpoints."""
    pytest.importorskip("submitit")
    from adarl.experiments.tune import run_tune

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setenv("PYTHONPATH", str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    spec = _spec(
        tmp_path, overrides=[*TINY, "collector.total_frames=900"], pruner={"name": "median", "n_startup_trials": 1}
    )
    out = tmp_path / "out"
    _add_unbeatable_trial(spec, out)
    said: list[str] = []
    result = run_tune(spec, output=out, launcher="submitit", launcher_options={"cluster": "local"}, log=said.append)
    assert result.states == {"COMPLETE": 1, "PRUNED": 1}, said
    _assert_pruned_and_checkpointed(out, 1, 0)
    assert (out / "submitit").is_dir()


def test_a_trial_whose_run_was_interrupted_from_outside_is_resumed_not_failed(tmp_path):
    """A trial's run stopped by SIGINT/SIGTERM from outside the study (status ``interrupted``, what
    ``execute_run`` gives a training that exits 130/143: tests/test_launchers.py) is said and left unfinished, and
    the next `adarl tune` resumes it; before, it failed the trial."""
    from adarl.experiments.launchers import LocalLauncher
    from adarl.experiments.tune import run_tune

    class InterruptedFromOutside(LocalLauncher):
        def run_watched(self, run, watch):
            run.status = "interrupted"
            run.message = "interrupted by SIGTERM (exit 143); resumes from its last checkpoint (log: x.log)"
            return run

    spec = _spec(tmp_path, n_trials=1)
    out = tmp_path / "out"
    said: list[str] = []
    first = run_tune(spec, output=out, log=said.append, launcher=InterruptedFromOutside())
    assert first.states == {"RUNNING": 1}, said
    assert any(line.startswith("[trial 0] interrupted by SIGTERM (exit 143)") for line in said), said
    assert not (out / "trials" / "trial-0000" / "tune_trial.json").is_file()  # neither failed nor complete

    said.clear()
    again = run_tune(spec, output=out, log=said.append)
    assert "0 of 1 trials done, 1 interrupted to resume" in said[0], said
    assert again.states == {"COMPLETE": 1} and again.resumed == [0]


def test_a_study_whose_output_closes_leaves_its_trial_to_resume_never_failed(tmp_path):
    """`adarl tune ... | head` once `head` has exited: the BrokenPipeError of a trial's line ends the study (exit 141
    in the CLI), its trial left RUNNING for the next `adarl tune` to resume, never told FAIL for a closed pipe."""
    from adarl.experiments.tune import run_tune

    said: list[str] = []

    def closed_after_the_first_line(line: str) -> None:
        if said:
            raise BrokenPipeError(32, "Broken pipe")
        said.append(line)

    out = tmp_path / "study"
    with pytest.raises(BrokenPipeError):
        run_tune(_spec(tmp_path), output=out, log=closed_after_the_first_line)
    trials = optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}").trials
    assert [(t.number, t.state.name) for t in trials] == [(0, "RUNNING")]


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file's bytes but the driver's lock (it names the process that holds it)."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != ".tune.lock"
    }


@pytest.mark.slow
def test_a_lost_or_emptied_study_db_is_rebuilt_from_the_trial_records_and_a_corrupt_one_refused(
    tmp_path, monkeypatch, capsys
):
    """Issue 46.3: with study.db deleted or emptied and the trial folders left, a rerun with another sampler seed
    "completed" each trial in 0.1 s by reusing the old run under other parameters (tune_trial.json, trials.csv and
    best_recipe.yaml said rank.beta=0.8145 while the run trained with 0.9043); a corrupt study.db gave a sqlalchemy
    traceback. Now the study is rebuilt from the records each trial keeps beside its run, and a corrupt one is
    refused by name."""
    from adarl.cli import main
    from adarl.experiments.tune import run_tune

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    out = tmp_path / "out"
    said: list[str] = []
    assert run_tune(_spec(tmp_path, n_trials=1), output=out, log=said.append).states == {"COMPLETE": 1}, said
    params = json.loads((out / "trials" / "trial-0000" / "tune_trial.json").read_text())["params"]
    trained = yaml.safe_load((out / "trials" / "trial-0000" / "recipe.yaml").read_text())
    assert trained["rank"]["beta"] == params["rank.beta"]
    before = _snapshot(out / "trials")
    db = out / "study.db"
    for how in ("deleted", "emptied"):
        db.unlink() if how == "deleted" else db.write_bytes(b"")
        other = _spec(tmp_path, n_trials=1, sampler={"name": "random", "seed": 7})
        said.clear()
        result = run_tune(other, output=out, log=said.append)
        assert result.states == {"COMPLETE": 1}, (how, said)
        assert result.best_number == 0 and result.best_params == params, (how, said)
        assert any("rebuilt" in line and "1 trial" in line for line in said), said
        with (out / "trials.csv").open() as fh:
            [row] = list(csv.DictReader(fh))
        assert float(row["rank.beta"]) == params["rank.beta"] and row["state"] == "COMPLETE"
        best = yaml.safe_load((out / "best_recipe.yaml").read_text())
        assert best["rank"]["beta"] == trained["rank"]["beta"]
        assert _snapshot(out / "trials") == before, how  # nothing trained again, no record rewritten
    # a second trial after the rebuild is trial 1, in a folder of its own
    db.write_bytes(b"this is not a database, " * 200)
    kept = _snapshot(out)
    assert main(["tune", str(_spec(tmp_path, n_trials=2)), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "study.db" in err and "is not a readable" in err and "trials/" in err, err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert _snapshot(out) == kept


@pytest.mark.slow
def test_the_base_recipe_is_pinned_by_content_and_read_from_the_specs_folder(tmp_path, monkeypatch, capsys):
    """Issue 46.5: a relative `recipe:` was read from the working folder, not the spec's; and an edit of the recipe
    the spec names went unnoticed (raise n_trials, rerun: exit 0, trial 3 trained [16, 16] beside trials 0-2 at
    [64, 64]). Now the study records its base recipe's content and refuses another by name, listing the keys."""
    from adarl.cli import main

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    specs = tmp_path / "specs"
    specs.mkdir()
    recipe = specs / "mine.yaml"
    recipe.write_text("extends: linear_cartpole_sac\n")
    spec = _spec(tmp_path, recipe="mine.yaml", n_trials=1)
    spec = spec.rename(specs / "tune.yaml")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the recipe is beside the spec, not here
    out = tmp_path / "out"
    assert main(["tune", str(spec), "-o", str(out)]) == 0, capsys.readouterr().err
    capsys.readouterr()
    recipe.write_text("extends: linear_cartpole_sac\nnetwork: {actor: {num_cells: [16, 16]}}\n")
    data = yaml.safe_load(spec.read_text())
    data["n_trials"] = 2
    spec.write_text(yaml.safe_dump(data))
    kept = _snapshot(out)
    assert main(["tune", str(spec), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        "another base recipe" in err and "network.actor.num_cells: [64, 64] in the study, [16, 16] in the spec" in err
    ), err
    assert not (out / "trials" / "trial-0001").exists()
    assert _snapshot(out) == kept


@pytest.mark.slow
def test_a_trial_stopped_by_a_full_disk_is_left_to_resume_and_the_command_fails(tmp_path, monkeypatch, capsys):
    """Issue 46.9: a trial whose run stopped on a full disk was told FAIL for good (a rerun never retried it) while
    `adarl tune` exited 0. Now the trial is left to resume, never FAIL, the command exits 1 in one line, and the next
    `adarl tune` resumes the trial from its checkpoint to its end."""
    import adarl.experiments.execute as execute
    from adarl.cli import main

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    spec, out = _spec(tmp_path, n_trials=1), tmp_path / "out"
    faults, metrics = REPO / "tests" / "faultfs.py", out / "trials" / "trial-0000" / "metrics"
    real = execute._cli  # the trial's `adarl run` with its metric files on a full disk (tests/faultfs.py)
    monkeypatch.setattr(execute, "_cli", lambda *a: [sys.executable, str(faults), str(metrics), "full", "0", "--", *a])
    assert main(["tune", str(spec), "-o", str(out)]) == 1
    captured = capsys.readouterr()
    [line] = [line for line in captured.err.splitlines() if line.startswith("adarl: error:")]
    assert "trial 0 stopped on a storage failure" in line and "run the same command again" in line, captured.err
    assert "Traceback" not in captured.err
    [said] = [s for s in captured.out.splitlines() if s.startswith("[trial 0] stopped, to resume:")]
    assert "No space left on device" in said, captured.out
    trials = optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}").trials
    assert [(t.number, t.state.name) for t in trials] == [(0, "RUNNING")]  # not FAIL: resumable
    monkeypatch.setattr(execute, "_cli", real)  # space freed
    assert main(["tune", str(spec), "-o", str(out)]) == 0, capsys.readouterr().err
    assert "0 of 1 trials done, 1 interrupted to resume" in capsys.readouterr().out
    trials = optuna.load_study(study_name="tiny", storage=f"sqlite:///{out / 'study.db'}").trials
    assert [(t.number, t.state.name) for t in trials] == [(0, "COMPLETE")]
