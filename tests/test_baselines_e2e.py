"""Every baseline algorithm runs end to end through the `adarl` command on a tiny budget (one env: Hopper)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from _helpers import adarl, tiny, tiny_ppo

REPO = Path(__file__).resolve().parents[1]


SAC_TINY = tiny(
    "collector.total_frames=300",
    "replay.size=1000",
    "eval.episodes=1",
    "eval.max_steps=30",
    "algorithm.update_after=null",
    drop=("rank.interval", "replay.warm_start.frames", "lr_schedule.warmup_steps"),
)
PPO_TINY = tiny_ppo()


def _run(recipe: str, overrides: list[str], out: Path) -> dict:
    proc = adarl("run", recipe, *overrides, "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["final_eval"] is not None and (out / "report.md").is_file()
    return summary


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["sac_full", "sac_fixed", "parseval", "sparse"])
def test_sac_baselines_run_from_the_cli(algorithm, tmp_path):
    out = tmp_path / algorithm
    summary = _run(f"baselines/hopper_{algorithm}", SAC_TINY, out)
    assert summary["updates"] == 200 and summary["rank_events"] == 0
    scalars = out / "metrics" / "scalars"
    assert (scalars / "train" / "loss_parseval.csv").is_file() == (algorithm == "parseval")


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ipm", "ds"])
def test_rnac_runs_from_the_cli_and_resumes(mode, tmp_path):
    out = tmp_path / mode
    summary = _run(f"baselines/hopper_rnac_{mode}", PPO_TINY, out)
    assert summary["frames"] == 256 and summary["updates"] == 4  # 2 batches x 1 epoch x 2 minibatches
    per_frame = 3 if mode == "ds" else 1  # DS probes m = 2 candidates before each real step
    assert summary["simulator_steps_per_frame"] == per_frame and summary["simulator_steps"] == 256 * per_frame
    assert f"simulator steps: {per_frame} per frame, {256 * per_frame} in all" in (out / "report.md").read_text()
    metric = "train/ipm_reward_shift" if mode == "ipm" else "train/ds_worst_fraction"
    assert (out / "metrics" / "scalars" / f"{metric}.csv").is_file()
    proc = adarl("eval", str(out), "--episodes", "1")  # rebuilds the PPO trainer from the checkpoint
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads((out / "eval_nominal.json").read_text())["frames"] == 256


def test_ppo_recipe_with_rank_adaptation_fails_before_writing(tmp_path):
    out = tmp_path / "never"
    proc = adarl("run", "baselines/hopper_rnac_ipm", "rank.enabled=true", "-o", str(out))
    assert proc.returncode != 0 and "rank.enabled" in proc.stderr and not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["ipm", "ds"])
def test_rnac_resume_from_a_mid_episode_checkpoint_is_exact(mode, tmp_path):
    """Resuming from the first of three 128-frame batches ends with the very networks, statistics and evaluation
    of the uninterrupted run (the live episode, the collector's carrier and the RNGs are in the checkpoint)."""
    import shutil

    import torch

    from adarl.runtime.config import load_recipe, save_resolved
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import OffPolicyTrainer, PPOTrainer

    recipe = load_recipe(
        f"baselines/hopper_rnac_{mode}",
        [
            "collector.total_frames=384",
            "collector.frames_per_batch=128",
            "algorithm.ppo.epochs=1",
            "eval.interval=100000",
            "eval.episodes=1",
            "eval.max_steps=20",
            "checkpoint.interval=128",
            "checkpoint.keep_last=5",
            "logging.log_interval=200",
        ],
    )
    full = RunDir.create(tmp_path / "full")
    save_resolved(recipe, full.recipe_path)
    PPOTrainer(recipe, full, quiet=True).train()
    shutil.copytree(full.path, tmp_path / "resumed")
    resumed = RunDir.open(tmp_path / "resumed")
    later = [p for p in resumed.checkpoints() if int(p.stem.split("-")[1]) > 128]
    assert len(later) == 2  # 256 and 384 frames: the run continues from 128, mid-episode
    for p in later:
        p.unlink()
    (resumed.path / "summary.json").unlink()
    OffPolicyTrainer.resume(resumed.path, quiet=True).train()
    a, b = full.load_checkpoint(full.checkpoints()[-1]), resumed.load_checkpoint(resumed.checkpoints()[-1])
    assert a["counters"]["frames"] == b["counters"]["frames"] == 384
    for net in ("actor", "critic"):
        for k, v in a[net].items():
            assert torch.equal(v, b[net][k]), (net, k)
    assert a["reward_scaler"]["returns"].equal(b["reward_scaler"]["returns"])
    assert (full.path / "eval.csv").read_text() == (resumed.path / "eval.csv").read_text()
    root = full.path / "metrics" / "scalars"
    metrics = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.csv"))
    assert "train/policy_gradient_loss.csv" in metrics and "train/value_loss.csv" in metrics  # SB3 PPO names
    for name in metrics:  # losses averaged over log_interval: a line at 256 frames and the final one at 384
        if name.startswith("time/"):
            continue  # wall-clock throughput
        assert (full.path / "metrics" / "scalars" / name).read_text() == (
            resumed.path / "metrics" / "scalars" / name
        ).read_text(), name


# ------------------------------------------------------------- the PPO loop's guards and interrupt (BaseTrainer)


def _ppo_trainer(path: Path, *extra: str):
    from adarl.runtime.config import load_recipe, save_resolved
    from adarl.runtime.run_folder.run_dir import RunDir
    from adarl.runtime.trainers import PPOTrainer

    recipe = load_recipe(
        "baselines/hopper_rnac_ipm",
        [
            "collector.total_frames=512",
            "collector.frames_per_batch=128",
            "algorithm.ppo.epochs=1",
            "eval.interval=100000",
            "eval.episodes=1",
            "eval.max_steps=20",
            "checkpoint.interval=128",
            *extra,
        ],
    )
    run = RunDir.create(path)
    save_resolved(recipe, run.recipe_path)
    return PPOTrainer(recipe, run, quiet=True)


def _on_loss_call(trainer, at_call: int, action) -> dict:
    """Run ``action(out)`` on the PPO loss's output at its ``at_call``-th forward (two per 128-frame batch here)."""
    calls = {"n": 0}

    def hook(module, args, out):
        calls["n"] += 1
        if calls["n"] == at_call:
            action(out)
        return out

    trainer.c.modules.loss.register_forward_hook(hook)
    return calls


@pytest.mark.parametrize("on_nonfinite", ["stop", "rollback"])
def test_ppo_divergence_guard_stops_or_rolls_back(tmp_path, on_nonfinite):
    import torch

    from adarl.runtime.guards import NonFiniteError
    from adarl.runtime.run_folder.run_dir import RunDir

    trainer = _ppo_trainer(tmp_path / "run", f"guards.on_nonfinite={on_nonfinite}", "guards.lr_factor=0.5")
    base_lr = trainer.c.optimizers["actor"].param_groups[0]["lr"]
    # the 5th minibatch: in the third batch, after the checkpoint at 256 frames
    _on_loss_call(trainer, 5, lambda out: out.set("loss_critic", out.get("loss_critic") * float("nan")))
    if on_nonfinite == "stop":
        with pytest.raises(NonFiniteError) as info:
            trainer.train()
        assert "loss_critic" in str(info.value) and "adarl resume" in str(info.value)
        state = RunDir.open(tmp_path / "run").load_latest_checkpoint()
        assert state["counters"]["frames"] == 256 < trainer.frames  # nothing written after the NaN
        assert all(torch.isfinite(v).all() for v in state["critic"].values())
        assert not (tmp_path / "run" / "summary.json").exists()
        return
    summary = trainer.train()  # the rollback rebuilds the loss (without the hook) from the 256-frame checkpoint
    assert trainer.rollbacks == 1 and summary["frames"] == 512
    assert trainer.c.schedulers["actor"].base_lrs == [base_lr * 0.5]
    assert RunDir.open(tmp_path / "run").load_latest_checkpoint()["counters"]["rollbacks"] == 1


def test_ppo_first_sigint_checkpoints_and_the_run_resumes(tmp_path):
    import signal

    from adarl.runtime.signals import RunInterrupted
    from adarl.runtime.trainers import BaseTrainer, PPOTrainer

    trainer = _ppo_trainer(tmp_path / "run", "checkpoint.interval=100000")
    _on_loss_call(trainer, 3, lambda out: os.kill(os.getpid(), signal.SIGINT))  # during the second batch
    with pytest.raises(RunInterrupted) as info:
        trainer.train()
    assert info.value.signum == signal.SIGINT and info.value.checkpoint.name == "ckpt-000000000256.pt"
    resumed = BaseTrainer.resume(tmp_path / "run", quiet=True)
    assert isinstance(resumed, PPOTrainer) and resumed.frames == 256
    assert resumed.train()["frames"] == 512
