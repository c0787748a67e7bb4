"""LeanCollector: the same actions as TorchRL's ProbabilisticActor, consistent transitions, random phase."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adarl.config import load_recipe
from adarl.errors import AdaRLValueError
from adarl.lean_collector import LeanCollector, wants_lean
from adarl.training import build_components

OVR = ["collector.total_frames=2000", "collector.init_random_frames=10", "collector.frames_per_batch=40",
       "replay.size=2000"]


@pytest.fixture(scope="module")
def comps():
    return build_components(load_recipe("quickstart", OVR))


def test_auto_picks_lean_for_one_box_env(comps):
    assert isinstance(comps.collector, LeanCollector)
    assert comps.collector.init_random_frames == 10


def test_policy_action_equals_probabilistic_actor_sample(comps):
    lean = LeanCollector(comps.env, comps.modules.actor, frames_per_batch=1)
    td = comps.env.reset()
    torch.manual_seed(7)
    a = lean.act(td)
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        torch.manual_seed(7)
        b = comps.modules.actor(td.clone())["action"]
    torch.testing.assert_close(a, b)


def test_batches_are_consistent_transitions(comps):
    lean = LeanCollector(comps.env, comps.modules.actor, frames_per_batch=40, init_random_frames=10, total_frames=120)
    batches = list(lean)
    assert [b.shape[0] for b in batches] == [40, 40, 40] and lean.frames == 120
    data = torch.cat(batches)
    for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "terminated"),
                ("next", "done"), ("next", "episode_reward")):
        assert key in data.keys(True), key
    done = data["next", "done"].squeeze(-1)
    same = torch.isclose(data["next", "observation"][:-1], data["observation"][1:]).all(-1)
    assert bool(same[~done[:-1]].all())  # s' of a step is s of the next one unless the episode ended
    assert data["action"].abs().max() <= 1.0


def test_trainer_wiring_and_fallbacks():
    comps = build_components(load_recipe("quickstart", OVR + ["collector.lean=false"]))
    assert not isinstance(comps.collector, LeanCollector)
    disc = build_components(load_recipe("cartpole_adarl", ["collector.total_frames=1000",
                                                           "collector.init_random_frames=250"]))
    assert not isinstance(disc.collector, LeanCollector)
    with pytest.raises(AdaRLValueError, match="collector.lean"):
        wants_lean(True, disc.env, disc.modules.actor)
