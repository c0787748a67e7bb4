"""End to end through the `adarl` command: a tiny AdaRL-SAC run, its run folder, eval, resume and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from _helpers import RANK_EVENTS, adarl, tiny

REPO = Path(__file__).resolve().parents[1]

# A few thousand frames, with the rank interval shrunk so that at least two rank events happen.
TINY = tiny(*RANK_EVENTS)


def _steps(csv_path: Path) -> list[int]:
    return [int(line.split(",")[0]) for line in csv_path.read_text().splitlines() if line and line != "step,value"]


@pytest.fixture(scope="module")
def tiny_run(rank_events_run) -> Path:
    """``adarl run quickstart TINY -o OUT --quiet``: conftest's rank_events_run (made once for this file,
    test_policy.py and test_export.py)."""
    out, proc = rank_events_run
    assert proc.args[3:] == ["run", "quickstart", *TINY, "-o", str(out), "--quiet"], proc.args
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert str(out) in proc.stdout
    return out


@pytest.mark.slow
def test_run_folder_has_every_output(tiny_run: Path):
    for name in (
        "recipe.yaml",
        "eval.csv",
        "ranks.json",
        "ranks.csv",
        "summary.json",
        "report.md",
        "plots/return.png",
        "plots/ranks.png",
        "plots/speed.png",
        "plugins.json",
    ):
        assert (tiny_run / name).is_file(), name
    for png in ("plots/return.png", "plots/ranks.png", "plots/speed.png"):
        assert (tiny_run / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = (tiny_run / "report.md").read_text()
    assert "![speed](plots/speed.png)" in report and "median updates/s" in report  # the cost between rank events
    assert json.loads((tiny_run / "plugins.json").read_text())["algorithm"]["package"] == "adarl"
    scalars = tiny_run / "metrics" / "scalars"
    for metric in (
        "rollout/ep_rew_mean",
        "rollout/ep_len_mean",
        "train/critic_loss",
        "train/actor_loss",
        "train/ent_coef",
        "eval/mean_reward",
        "dynamics/torso_length",
        "warm_start/frames",
        "rank/actor.layer0",
        "rank/critic.layer1",
        "time/fps",
    ):
        assert (scalars / f"{metric}.csv").is_file(), metric
    # The perturbation really varied the dynamics seen in training.
    header, *rows = (scalars / "dynamics/torso_length.csv").read_text().splitlines()
    assert header == "step,value"
    torso = [float(line.split(",")[1]) for line in rows]
    assert max(torso) - min(torso) > 0.01
    # The resolved recipe loads back to the same recipe (overrides applied).
    from adarl.runtime.config import load_recipe

    resolved = load_recipe(str(tiny_run / "recipe.yaml"))
    assert resolved.collector.total_frames == 1600 and resolved.rank.interval == 400


@pytest.mark.slow
def test_ranks_fell_and_evaluation_ran(tiny_run: Path):
    history = json.loads((tiny_run / "ranks.json").read_text())
    assert len(history) >= 2, "at least two rank events"
    summary = json.loads((tiny_run / "summary.json").read_text())
    assert summary["rank_events"] == len(history)  # every event is recorded, also one where nothing changed
    first = {layer["layer"]: layer["old_rank"] for layer in history[0]["layers"]}
    assert set(summary["ranks"]) == set(first)
    assert all(summary["ranks"][k] <= first[k] for k in first) and summary["ranks"] != first
    for event in history:  # the acceptance step's record, for actor and critic layers alike
        assert {layer["network"] for layer in event["layers"]} == {"actor", "critic"}
        for layer in event["layers"]:
            assert layer["tolerance"] == (0.05 if layer["network"] == "actor" else 0.02)
            assert layer["candidate"] <= layer["old_rank"]
            if layer["new_rank"] < layer["old_rank"]:
                assert 0 <= layer["error"] <= layer["tolerance"]
    import csv as _csv

    rows = list(_csv.DictReader((tiny_run / "ranks.csv").open()))
    assert len(rows) == sum(len(e["layers"]) for e in history)
    critic = [r for r in rows if r["network"] == "critic"]
    assert critic and all(r["retained_energy"] and r["truncation_error"] and r["tolerance"] for r in critic)
    # The budget is checked between batches; a warm start at the last event may pass it by its own frames.
    assert 1600 <= summary["frames"] <= 1600 + 100 and summary["updates"] > 0
    evals = (tiny_run / "eval.csv").read_text().splitlines()
    assert len(evals) >= 3  # header + an intermediate + the final evaluation
    assert summary["final_eval"]["episodes"] == 2
    assert torch.isfinite(torch.tensor(summary["final_eval"]["mean"]))
    report = (tiny_run / "report.md").read_text()
    assert "Evaluation on nominal dynamics" in report and "Rank events" in report


@pytest.mark.slow
def test_checkpoint_holds_ranks_and_loads_safely(tiny_run: Path):
    from adarl.runtime.run_folder.run_dir import RunDir

    run = RunDir.open(tiny_run)
    ckpts = run.checkpoints()
    assert ckpts and len(ckpts) <= 3  # keep_last
    state = run.load_checkpoint(ckpts[-1])
    assert state["counters"]["frames"] == json.loads((tiny_run / "summary.json").read_text())["frames"]
    summary = json.loads((tiny_run / "summary.json").read_text())
    assert state["adapter"]["ranks"] == summary["ranks"]
    assert {"loss", "optimizers", "schedulers", "rng", "dynamics"} <= set(state)


@pytest.mark.slow
def test_eval_command(tiny_run: Path):
    proc = adarl("eval", str(tiny_run), "--episodes", "2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    payload = json.loads((tiny_run / "eval_nominal.json").read_text())
    assert payload["episodes"] == 2 and len(payload["returns"]) == 2


@pytest.mark.slow
def test_resume_continues_without_duplicated_metrics(tmp_path: Path):
    out = tmp_path / "run"
    proc = adarl("run", "quickstart", *TINY, "collector.total_frames=1000", "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Pretend the run died after its checkpoint at 500 frames: drop the later checkpoint, keep later metrics.
    from adarl.runtime.run_folder.run_dir import RunDir

    run = RunDir.open(out)
    for ckpt in run.checkpoints():
        if int(ckpt.stem.split("-")[1]) > 500:
            ckpt.unlink()
    proc = adarl("resume", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] >= 1000
    scalars = out / "metrics" / "scalars"
    files = sorted(scalars.rglob("*.csv"))
    assert scalars / "rollout" / "ep_rew_mean.csv" in files
    for csv in files:
        steps = _steps(csv)
        group = csv.relative_to(scalars).parts[0]  # rank events: two in one batch share its frame
        assert steps == sorted(steps), f"{csv.name} has steps out of order after resume"
        assert len(steps) == len(set(steps)) or group in ("rank", "rank_error", "warm_start"), (
            f"{csv.name} has duplicated steps"
        )


@pytest.mark.slow
def test_refuses_to_overwrite(tiny_run: Path):
    before = sorted(p.name for p in tiny_run.iterdir())
    proc = adarl("run", "quickstart", *TINY, "-o", str(tiny_run), "--quiet")
    assert proc.returncode != 0
    assert "already exists" in proc.stderr and "--overwrite" in proc.stderr
    assert sorted(p.name for p in tiny_run.iterdir()) == before


@pytest.mark.parametrize(
    "override, expected",
    [
        ("rank.betta=0.9", ["rank.betta", "beta"]),
        ("rank.beta=1.5", ["rank.beta", "1.5", "(0, 1)"]),
        ("network.actor.rank=100", ["rank", "100"]),
        ("env.id=Nope-v5", ["env.id", "Nope-v5", "Hopper-v5"]),
        ("env.perturbation.schedule={kind: fixed, values: {bogus_length: 1.0}}", ["bogus_length", "torso_length"]),
        # Valid for the schema but larger than Hopper's 11 inputs allow: caught when the network is built.
        ("network.actor.rank=20", ["rank", "20", "11"]),
    ],
)
def test_bad_recipe_exits_nonzero_and_writes_nothing(tmp_path: Path, override: str, expected: list[str]):
    out = tmp_path / "should_not_exist"
    proc = adarl("run", "quickstart", override, "-o", str(out), "--quiet", cwd=tmp_path)
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    for word in expected:
        assert word in proc.stderr, (word, proc.stderr)
    assert not out.exists()
    assert not (tmp_path / "runs").exists()


def test_recipes_and_show_and_help():
    proc = adarl("recipes")
    assert proc.returncode == 0
    for name in ("quickstart", "hopper_adarl", "walker2d_adarl", "ant_adarl", "humanoid_adarl", "cartpole_adarl"):
        assert name in proc.stdout
    proc = adarl("show", "hopper_adarl", "rank.beta=0.9")
    assert proc.returncode == 0 and "beta: 0.9" in proc.stdout
    for sub in ([], ["run"], ["resume"], ["eval"], ["recipes"], ["show"], ["report"]):
        proc = adarl(*sub, "--help")
        assert proc.returncode == 0 and "usage: adarl" in proc.stdout
