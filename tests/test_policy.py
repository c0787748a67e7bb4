"""A trained policy in your own code and on screen (issue 20): `adarl.load_policy` gives the TorchRL actor with the
truncated ranks restored and builds no env, buffer or collector; `adarl play` renders it headless to an MP4 with
gymnasium's RecordVideo. The tiny run behind them is made with `--quiet`, which must print nothing but its result."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import _helpers
import pytest
import torch
from _helpers import adarl
from tensordict import TensorDict

REPO = Path(__file__).resolve().parents[1]
TINY = _helpers.tiny(*_helpers.RANK_EVENTS)


@pytest.fixture(scope="module")
def tiny(rank_events_run):
    """``adarl run quickstart TINY -o OUT --quiet``: conftest's rank_events_run (made once for this file,
    test_cli_e2e.py and test_export.py)."""
    out, proc = rank_events_run
    assert proc.args[3:] == ["run", "quickstart", *TINY, "-o", str(out), "--quiet"], proc.args
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc


def test_quiet_run_prints_only_its_result(tiny):
    out, proc = tiny
    assert proc.stderr == "", proc.stderr  # no TorchRL INFO line, no target-updater warning, no progress bar
    lines = proc.stdout.splitlines()
    assert len(lines) == 3 and lines[0].startswith("run finished") and str(out) in lines[2]
    assert "actor.layer0=" in lines[0] and "module" not in lines[0]


def _actor_ranks(actor) -> list[int]:
    from adarl.core.lowrank import LowRankLinear

    return [m.rank for m in actor.modules() if isinstance(m, LowRankLinear)]


def test_load_policy_restores_truncated_ranks_without_building_env_buffer_or_collector(tiny, monkeypatch):
    import gymnasium
    import torchrl.collectors
    import torchrl.data
    import torchrl.envs.libs.gym

    import adarl
    import adarl.runtime.builders.sac

    out, _ = tiny
    summary = json.loads((out / "summary.json").read_text())
    names = summary["layer_names"]
    want = [summary["ranks"][p] for p in sorted(names, key=names.get) if names[p].startswith("actor.")]
    assert want != [11, 64], "the tiny run should have truncated an actor layer"

    def refuse(*args, **kwargs):
        raise AssertionError("load_policy built an env, a buffer or a collector")

    monkeypatch.setattr(adarl.runtime.builders.sac, "build_sac_components", refuse)
    monkeypatch.setattr(gymnasium, "make", refuse)
    monkeypatch.setattr(torchrl.envs.libs.gym.GymEnv, "__init__", refuse)
    monkeypatch.setattr(torchrl.collectors.Collector, "__init__", refuse)
    monkeypatch.setattr(torchrl.data.TensorDictReplayBuffer, "__init__", refuse)
    actor = adarl.load_policy(out)  # fast because it builds none of the above (refused), not timed
    from tensordict.nn import TensorDictModuleBase

    assert isinstance(actor, TensorDictModuleBase)
    assert _actor_ranks(actor) == want
    state = torch.load(sorted((out / "checkpoints").glob("ckpt-*.pt"))[-1], weights_only=True)["state"]
    for name, p in actor.named_parameters():
        assert torch.equal(p, state["loss"][f"actor_network_params.{name}"]), name
        assert not p.requires_grad
    td = actor(TensorDict(observation=torch.zeros(4, 11), batch_size=[4]))
    assert td["action"].shape == (4, 3) and bool((td["action"].abs() <= 1).all())
    assert torch.equal(td["action"], actor(TensorDict(observation=torch.zeros(4, 11), batch_size=[4]))["action"])


def test_loaded_policy_acts_as_the_trained_one_and_in_gymnasium(tiny):
    import gymnasium as gym
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    import adarl
    from adarl.runtime.trainers import OffPolicyTrainer

    out, _ = tiny
    actor = adarl.load_policy(out)
    trainer = OffPolicyTrainer.resume(out, quiet=True, truncate_metrics=False)
    try:
        obs = TensorDict(observation=torch.randn(32, 11), batch_size=[32])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            assert torch.allclose(actor(obs.clone())["action"], trainer.c.modules.actor(obs.clone())["action"])
    finally:
        trainer.close()
    env = gym.make("Hopper-v5")
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        action = actor(TensorDict(observation=torch.as_tensor(obs, dtype=torch.float32)))["action"]
        obs, reward, terminated, truncated, _ = env.step(action.numpy())
        if terminated or truncated:
            break
    env.close()


def test_load_policy_best_a_checkpoint_file_and_an_older_checkpoint(tiny, tmp_path):
    import shutil

    import adarl
    from adarl.errors import AdaRLValueError, CheckpointError
    from adarl.runtime.policy import load_policy_with_info

    out, _ = tiny
    best = load_policy_with_info(out, "best")
    assert best.checkpoint == out / "checkpoints" / "best.pt" and best.frames > 0
    latest = sorted((out / "checkpoints").glob("ckpt-*.pt"))[-1]
    assert load_policy_with_info(latest).frames == json.loads((out / "summary.json").read_text())["frames"]
    with pytest.raises(AdaRLValueError, match=r"which must be one of \['latest', 'best'\], got 'worst'"):
        adarl.load_policy(out, which="worst")
    with pytest.raises(CheckpointError, match="neither a run folder nor a checkpoint file"):
        adarl.load_policy(tmp_path / "nothing")
    # a checkpoint written before checkpoints held the policy's specs: the gymnasium env's spaces are used
    old = tmp_path / "old"
    shutil.copytree(out, old, ignore=shutil.ignore_patterns("rb-*"))
    ckpt = sorted((old / "checkpoints").glob("ckpt-*.pt"))[-1]
    payload = torch.load(ckpt, weights_only=True)
    payload["state"].pop("policy_specs")
    payload["replay_buffer"] = False
    torch.save(payload, ckpt)
    obs = TensorDict(observation=torch.randn(8, 11), batch_size=[8])
    a, b = adarl.load_policy(ckpt), adarl.load_policy(latest)
    assert torch.equal(a(obs.clone())["action"], b(obs.clone())["action"])


def _headless_backend() -> str | None:
    """The MUJOCO_GL backend that renders here (EGL first, then OSMesa), or None."""
    code = (
        "import gymnasium as gym\n"
        "e = gym.make('Hopper-v5', render_mode='rgb_array', width=32, height=32)\n"
        "e.reset(seed=0)\n"
        "assert e.render().shape == (32, 32, 3)\n"
    )
    for gl in ("egl", "osmesa"):
        proc = subprocess.run(
            [sys.executable, "-c", code],
            env={**os.environ, "MUJOCO_GL": gl},
            capture_output=True,
            text=True,
            timeout=120,
        )
        if proc.returncode == 0:
            return gl
    return None


def test_play_renders_headless_to_one_video(tiny, tmp_path):
    pytest.importorskip("moviepy", reason="adarl play --video needs moviepy (pip install 'adarl[video]')")
    gl = _headless_backend()
    if gl is None:
        pytest.skip("MuJoCo cannot render headless here: neither MUJOCO_GL=egl (libEGL) nor osmesa (libOSMesa)")
    out, _ = tiny
    video = tmp_path / "videos" / "hopper.mp4"
    proc = adarl(
        "play",
        str(out),
        "--video",
        str(video),
        "--episodes",
        "2",
        "--max-steps",
        "10",
        "--size",
        "64x48",
        "--perturb",
        "torso_length=0.5",
        cwd=tmp_path,
        env={"MUJOCO_GL": gl},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "torso_length=0.5" in proc.stdout and "episode 1: return" in proc.stdout and str(video) in proc.stdout
    from moviepy import VideoFileClip

    clip = VideoFileClip(str(video))
    try:
        assert list(clip.size) == [64, 48]
        frames = list(clip.iter_frames())
    finally:
        clip.close()
    assert len(frames) == 2 * (10 + 1)  # each episode's reset frame and its 10 steps
    assert max(float(f.mean()) for f in frames) > 10  # not a black video


def test_play_without_video_and_its_errors(tiny, tmp_path, capsys, monkeypatch):
    from adarl.cli import main

    out, _ = tiny
    proc = adarl("play", str(out), "--max-steps", "5", "--which", "best", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "episode 0: return" in proc.stdout and "best.pt" in proc.stdout
    monkeypatch.chdir(tmp_path)
    for args, words in (  # bad input: exit 2 and one line naming it (in this process: the CLI's own main)
        (["--perturb", "bogus_length=1"], ["bogus_length", "torso_length"]),
        (["--perturb", "torso_length"], ["PARAM=VALUE"]),
        (["--video", "out.avi"], [".mp4"]),
        (["--episodes", "0"], ["episodes", ">= 1"]),
    ):
        capsys.readouterr()
        assert main(["play", str(out), *args]) == 2, args
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err, (args, err)
        for word in words:
            assert word in err, (word, err)
    assert not (tmp_path / "out.avi").exists()


@pytest.mark.parametrize(
    "recipe, overrides, obs_dim",
    [
        (
            "baselines/hopper_rnac_ipm",
            [
                "collector.total_frames=256",
                "collector.frames_per_batch=128",
                "algorithm.ppo.epochs=1",
                "eval.interval=256",
                "eval.episodes=1",
                "eval.max_steps=20",
                "checkpoint.interval=256",
            ],
            11,
        ),
        (
            "cartpole_adarl",
            [
                "collector.total_frames=400",
                "collector.init_random_frames=200",
                "collector.frames_per_batch=100",
                "rank.interval=100",
                "replay.warm_start.frames=100",
                "eval.interval=400",
                "eval.episodes=1",
                "eval.max_steps=20",
            ],
            4,
        ),
    ],
)
def test_load_policy_of_a_ppo_run_and_a_discrete_run(recipe, overrides, obs_dim, tmp_path):
    from adarl.runtime.policy import load_policy, load_policy_with_info

    out = tmp_path / "run"
    proc = adarl("run", recipe, *overrides, "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    loaded = load_policy_with_info(out)
    state = torch.load(loaded.checkpoint, weights_only=True)["state"]
    if recipe.startswith("baselines/"):  # PPO: the actor's own state dict, running obs normalisation included
        assert all(torch.equal(v, state["actor"][k]) for k, v in loaded.actor.state_dict().items())
    else:
        for name, p in loaded.actor.named_parameters():
            assert torch.equal(p, state["loss"][f"actor_network_params.{name}"]), name
    action = load_policy(out)(TensorDict(observation=torch.randn(obs_dim)))["action"]
    assert action.shape == ((2,) if recipe == "cartpole_adarl" else (3,))
