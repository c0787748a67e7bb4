"""The fast evaluation path (adarl.fast.evaluation) gives TorchRL's env.rollout returns and lengths, bit for bit."""

from __future__ import annotations

import pytest
import torch

from adarl.envs.factory import make_env, make_eval_env
from adarl.fast import evaluation as fast_evaluation
from adarl.runtime import evaluation
from adarl.runtime.builders.sac import make_sac_modules
from adarl.runtime.config import load_recipe


@pytest.fixture(scope="module")
def actor():
    recipe = load_recipe("quickstart", [])
    torch.manual_seed(3)
    return make_sac_modules(recipe, make_env("Hopper-v5", seed=0)).actor


def _both(actor, build, episodes, max_steps, monkeypatch):
    fast = evaluation.evaluate_policy(actor, build(), episodes=episodes, max_steps=max_steps)
    with monkeypatch.context() as m:
        m.setattr(evaluation, "episode_runner", lambda policy, env: None)  # TorchRL's env.rollout path
        slow = evaluation.evaluate_policy(actor, build(), episodes=episodes, max_steps=max_steps)
    return fast, slow


@pytest.mark.parametrize(
    "build",
    [
        lambda: make_eval_env("Hopper-v5", "paper", seed=4),  # the nominal dynamics, as a run evaluates
        lambda: make_eval_env("Hopper-v5", values={"torso_length": 0.3}, seed=4),  # a sweep point
        lambda: make_env("Hopper-v5", preset="paper", seed=4),  # dynamics drawn at every reset
        lambda: make_env("Hopper-v5", preset="none", seed=4, max_episode_steps=25),  # gymnasium's time limit
    ],
    ids=["nominal", "sweep-point", "perturbed", "time-limit"],
)
def test_fast_episodes_equal_torchrls(actor, build, monkeypatch):
    assert fast_evaluation.episode_runner(actor, build()) is not None  # the fast path is the one under test
    fast, slow = _both(actor, build, episodes=4, max_steps=1000, monkeypatch=monkeypatch)
    assert fast.returns == slow.returns and fast.lengths == slow.lengths
    assert len(set(fast.returns)) > 1  # the episodes differ (fresh initial states, dynamics)


def test_max_steps_cuts_an_episode_as_torchrl_does(actor, monkeypatch):
    fast, slow = _both(actor, lambda: make_eval_env("Hopper-v5", "paper", seed=1), 3, 7, monkeypatch)
    assert fast.lengths == slow.lengths == [7, 7, 7] and fast.returns == slow.returns


def test_other_policies_and_envs_keep_torchrls_path(actor):
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import RandomPolicy

    env = make_env("Hopper-v5", seed=0)
    assert fast_evaluation.episode_runner(RandomPolicy(env.action_spec), env) is None
    assert fast_evaluation.episode_runner(actor, GymEnv("Hopper-v5")) is None
    result = evaluation.evaluate_policy(RandomPolicy(env.action_spec), env, episodes=2, max_steps=20)
    assert len(result.returns) == 2
