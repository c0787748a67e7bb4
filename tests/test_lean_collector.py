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


def _env_and_actor(seed):
    c = build_components(load_recipe("quickstart", OVR + [f"seed={seed}"]))
    return c.env, c.modules.actor


def test_overlap_collects_the_next_batch_with_the_policy_at_handover():
    # X prefetches in a thread while the "updates" (in-place weight changes) run; Y replays the same schedule
    # by hand, synchronously: batch k + 1 from the snapshot taken when batch k was handed over.
    import copy

    env_x, actor_x = _env_and_actor(5)
    env_y, actor_y = _env_and_actor(5)
    actor_y.load_state_dict(actor_x.state_dict())
    x = LeanCollector(env_x, actor_x, frames_per_batch=25, init_random_frames=0, overlap=True, noise_seed=9)
    y = LeanCollector(env_y, actor_y, frames_per_batch=25, init_random_frames=0)
    noise_y = torch.Generator().manual_seed(9)
    torch.manual_seed(0)
    x_batches, y_batches = [], []
    snapshot = copy.deepcopy(y.net)  # the policy for batch 0
    for k, batch in enumerate(x):
        handover = copy.deepcopy(y.net)  # the policy when batch k is handed over
        with torch.no_grad():  # the "updates" of batch k, at once, while X's thread collects batch k + 1
            for px, py in zip(actor_x.parameters(), actor_y.parameters()):
                step = 0.05 * torch.randn_like(px)
                px.add_(step)
                py.add_(step)
        x_batches.append(batch)
        y_batches.append(y._collect(snapshot, noise_y))
        snapshot = handover
        if k == 4:
            break
    x.shutdown()
    for k, (a, b) in enumerate(zip(x_batches, y_batches)):
        for key in ("observation", "action", ("next", "observation"), ("next", "reward")):
            assert torch.equal(a.get(key), b.get(key)), (k, key)


def test_overlap_state_dict_keeps_the_prefetched_batch():
    env, actor = _env_and_actor(6)
    x = LeanCollector(env, actor, frames_per_batch=20, init_random_frames=0, overlap=True, noise_seed=1)
    it = iter(x)
    next(it)  # batch 1 handed over, batch 2 being prefetched
    state = x.state_dict()
    assert state["prefetched"] is not None and x.frames == 40
    batch2 = next(it)
    env2, actor2 = _env_and_actor(6)
    y = LeanCollector(env2, actor2, frames_per_batch=20, init_random_frames=0, overlap=True, noise_seed=1)
    y.load_state_dict(state)
    assert torch.equal(next(iter(y)).get("action"), batch2.get("action"))
    x.shutdown()
    y.shutdown()
    assert x._thread is None and y._thread is None


def test_overlap_needs_the_lean_collector():
    with pytest.raises(AdaRLValueError, match="collector.overlap"):
        build_components(load_recipe("quickstart", OVR + ["collector.overlap=true", "collector.lean=false"]))
