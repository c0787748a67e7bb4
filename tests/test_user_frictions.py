"""Frictions a new user met (issue 48, point 6), each reproduced as they met it: the command they typed, what it
said, and what it says now."""

from __future__ import annotations

import pytest

from adarl import cli
from adarl.errors import AdaRLValueError, RecipeError, did_you_mean
from adarl.runtime.config import load_recipe


def test_a_mistyped_recipe_name_says_the_did_you_mean_before_a_short_list(capsys):
    """`adarl show quickstrat` printed a 1762-character line (every recipe) before its did-you-mean."""
    with pytest.raises(RecipeError) as err:
        load_recipe("quickstrat")
    said = str(err.value)
    assert said.index("did you mean 'quickstart'") < said.index("available:")
    assert len(said) < 500 and "`adarl recipes` lists them" in said
    assert cli.main(["show", "quickstrat"]) == 2
    line = capsys.readouterr().err
    assert "did you mean 'quickstart'" in line and len(line) < 500


def test_a_run_folder_that_does_not_exist_is_named_so(tmp_path, capsys):
    """`adarl eval runs/nope` said "not an adarl run folder (no recipe.yaml in it)", exit 1, for a folder that does
    not exist: bad input (exit 2), said as it is; a folder without a recipe.yaml is still "not an adarl run folder"."""
    from adarl.runtime.run_folder.run_dir import RunDir

    with pytest.raises(AdaRLValueError, match=r"run folder '.*nope' does not exist"):
        RunDir.open(tmp_path / "nope")
    assert cli.main(["eval", str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["eval", str(tmp_path / "empty")]) == 1
    assert "is not an adarl run folder (no recipe.yaml in it)" in capsys.readouterr().err


def test_a_mistyped_or_shortened_parameter_gets_a_did_you_mean():
    """`--sweep torso_lenght=...` and `--perturb torso=...` named the allowed parameters with no did-you-mean."""
    from adarl.envs.registry import validate_values
    from adarl.experiments.sweep import sweep_policy

    assert did_you_mean("torso", ["foot_length", "torso_length"]) == "; did you mean 'torso_length'?"
    assert did_you_mean("to", ["torso_length"]) == ""  # too short to point at one name
    with pytest.raises(AdaRLValueError, match=r"unknown parameter 'torso'.*did you mean 'torso_length'"):
        validate_values("Hopper-v5", {"torso": 0.3})  # what --perturb torso=0.3 checks with
    with pytest.raises(AdaRLValueError, match=r"unknown sweep parameter 'torso_lenght'.*did you mean 'torso_length'"):
        sweep_policy(None, "Hopper-v5", [("torso_lenght", [0.3, 0.4])], nominal={}, episodes=1)


def test_one_evaluation_episode_is_said_without_nan_or_plural():
    """One evaluation episode printed "95% CI ± nan" and "1 episodes"."""
    from adarl.runtime.evaluation import EvalResult, describe_returns

    one = EvalResult([3012.4], [1000])
    said = describe_returns(one.mean, one.std, one.ci95, 1)
    assert "nan" not in said and "1 episodes" not in said and said.startswith("3012.4 over 1 episode")
    two = EvalResult([3000.0, 3010.0], [1000, 1000])
    assert describe_returns(two.mean, two.std, two.ci95, 2).startswith("3005.0 ± 7.1 (95% CI ± 63.5) over 2 episodes")


def test_a_run_folder_holding_its_default_export_is_overwritten_like_any_run_folder(tmp_path):
    """After `adarl export runs/q1`, `adarl run ... -o runs/q1 --overwrite` refused: "holds policy.pt, which adarl
    did not write". The export's default files are adarl's own; a file adarl never writes still stops it."""
    from adarl.errors import AdaRLError
    from adarl.runtime.config import save_resolved
    from adarl.runtime.run_folder.run_dir import RunDir

    run = tmp_path / "q1"
    run.mkdir()
    save_resolved(load_recipe("quickstart"), run / "recipe.yaml")
    for name in ("policy.pt", "policy.pt2", "policy.onnx"):
        (run / name).write_bytes(b"an export")
    (run / "notes.txt").write_text("mine")
    with pytest.raises(AdaRLError, match=r"notes\.txt"):
        RunDir.create(run, overwrite=True)
    assert (run / "notes.txt").exists() and (run / "policy.pt").exists()  # nothing removed
    (run / "notes.txt").unlink()
    RunDir.create(run, overwrite=True).unlock()
    assert not (run / "policy.pt").exists()


def test_a_budget_below_the_recipes_random_frames_is_refused_by_name():
    """`adarl run baselines/hopper_td3 collector.total_frames=8000 eval.interval=4000` ran 12950 frames: the recipe's
    10000 random frames were above the lowered budget, silently. Refused naming the key and the budget (a counted
    warm start never runs past the budget either: tests/test_faults.py)."""
    with pytest.raises(RecipeError, match=r"collector.init_random_frames = 10000: must be <= collector.total_frames"):
        load_recipe("baselines/hopper_td3", ["collector.total_frames=8000", "eval.interval=4000"])
    ok = load_recipe("baselines/hopper_td3", ["collector.total_frames=8000", "collector.init_random_frames=1000"])
    assert ok.collector.total_frames == 8000


def test_the_composition_guides_first_example_sets_up_without_torchrls_warnings(tmp_path):
    """docs/composition.md's first example printed TorchRL's "No target network updater" warning and an InitTracker
    FutureWarning. Its set-up (everything before the training loop; the loop is the same calls) runs with both
    turned into errors."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "composition.md").read_text()
    first = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    setup = first[: first.index("frames = 0")] + "next(iter(collector))\ncollector.shutdown()\n"
    (tmp_path / "example.py").write_text(setup)
    strict = ["-W", "error::FutureWarning", "-W", "error:No target network updater:UserWarning"]
    done = subprocess.run(
        [sys.executable, *strict, str(tmp_path / "example.py")], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]


def test_the_tune_history_plot_has_whole_trial_ticks(tmp_path, monkeypatch):
    """optimization_history.png of a 3-trial study had fractional trial ticks (0.5, 1.5, ...)."""
    import matplotlib.pyplot as plt
    import optuna

    from adarl.experiments.tune import _outputs
    from adarl.experiments.tune._spec import load_tune_spec

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="maximize")
    for value in (1.0, 3.0, 2.0):
        study.add_trial(optuna.trial.create_trial(value=value))
    ticks = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: (ticks.extend(fig.axes[0].get_xticks()), close(fig)))
    _outputs._plot_history(study, load_tune_spec("cartpole_beta"), tmp_path / "history.png")
    assert ticks and all(float(t).is_integer() for t in ticks), ticks


def test_progress_csv_is_one_wide_table_of_every_scalar_that_follows_a_resumes_truncation(tmp_path):
    """SB3's progress.csv: a row per logged step, time/total_timesteps first, a column per metric, blank where a
    metric was not logged; made from the per-metric files, so a resume's truncation reaches it too."""
    import pandas as pd

    from adarl.runtime.run_folder.run_dir import RunDir

    run = RunDir(tmp_path)
    scalars = tmp_path / "metrics" / "scalars"
    rows = {
        "rollout/ep_rew_mean": [(100, 1.5), (200, 2.5), (300, 3.5)],
        "eval/mean_reward": [(200, 10.0)],
        "eval/mean_ep_length": [(200, 50.0)],
        "time/time_elapsed": [(100, 0.25), (200, 0.5), (300, 0.75)],
    }
    for name, values in rows.items():
        (scalars / name).parent.mkdir(parents=True, exist_ok=True)
        (scalars / f"{name}.csv").write_text("step,value\n" + "".join(f"{s},{v}\n" for s, v in values))
    table = pd.read_csv(run.write_progress())
    assert list(table.columns) == ["time/total_timesteps", *sorted(rows)]
    assert table["time/total_timesteps"].tolist() == [100, 200, 300]
    assert table["rollout/ep_rew_mean"].tolist() == [1.5, 2.5, 3.5]
    assert table["eval/mean_reward"].isna().tolist() == [True, False, True] and table["eval/mean_reward"][1] == 10.0
    run.truncate_metrics(200)  # what a resume from the checkpoint at 200 frames does first
    table = pd.read_csv(run.write_progress())
    assert table["time/total_timesteps"].tolist() == [100, 200]
