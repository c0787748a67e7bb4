"""adarl.fast.direct_env: the LeanCollector's direct stepping hands out TorchRL's batches and carrier, bit for bit."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import RewardScaling

from adarl.envs import dynamics_state_dict, load_dynamics_state_dict, make_env
from adarl.envs.state import env_state_dict, load_env_state_dict
from adarl.errors import AdaRLValueError
from adarl.fast.collector import LeanCollector, _tanh_normal_action
from adarl.fast.direct_env import direct_stepper
from adarl.runtime.builders import make_sac_actor


def _parts(env_id="Hopper-v5", preset="paper", max_episode_steps=30, seed=3):
    env = make_env(env_id, preset=preset, seed=seed, max_episode_steps=max_episode_steps)
    torch.manual_seed(0)
    return env, make_sac_actor(env)


def _reference(env, actor, batches, frames_per_batch, init_random_frames, td=None, frames=0):
    """The LeanCollector's loop before the direct path: TorchRL's step_and_maybe_reset, actions from the actor's
    network called as a module, torch.stack of the frames."""
    net = actor.module[0].module
    box = LeanCollector(env, actor, frames_per_batch=1, direct=False)._box
    out = []
    for _ in range(batches):
        steps = []
        for _ in range(frames_per_batch):
            if td is None:
                td = env.reset()
            with torch.no_grad():
                action = (
                    env.action_spec.rand()
                    if frames < init_random_frames
                    else _tanh_normal_action(net, td.get("observation"), None, box)
                )
            td.set("action", action)
            frame, td = env.step_and_maybe_reset(td)
            steps.append(frame)
            frames += 1
        out.append(torch.stack(steps).contiguous())
    return out, td


def _assert_same(a, b, what=""):
    """Same keys in the same order, same batch sizes and devices, same dtypes, shapes and values (torch.equal)."""
    assert list(a.keys(True, True)) == list(b.keys(True, True)), what
    assert a.batch_size == b.batch_size and a.device == b.device, what
    for key in a.keys(True, True):
        x, y = a.get(key), b.get(key)
        assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y), (what, key)
    for key in a.keys(True):
        if key not in a.keys(True, True):  # sub-TensorDicts
            assert a.get(key).batch_size == b.get(key).batch_size and a.get(key).device == b.get(key).device, key


def _collect(collector, batches):
    it = iter(collector)
    return [next(it) for _ in range(batches)]


@pytest.mark.parametrize("preset", ["paper", "none"])
def test_direct_batches_and_carrier_equal_torchrls_bit_for_bit(preset):
    # 2500 frames: a random phase, then policy actions; Hopper terminates often, the 30-step cap truncates
    env, actor = _parts(preset=preset)
    torch.manual_seed(1)
    lean = LeanCollector(env, actor, frames_per_batch=50, init_random_frames=300)
    assert lean.direct
    got = _collect(lean, 50)
    rng = torch.get_rng_state()
    env_r, actor_r = _parts(preset=preset)
    torch.manual_seed(1)
    want, carrier = _reference(env_r, actor_r, 50, 50, 300)
    assert torch.equal(rng, torch.get_rng_state())  # the same draws from torch's global RNG
    for k, (a, b) in enumerate(zip(got, want)):
        _assert_same(a, b, f"batch {k}")
    _assert_same(lean._td, carrier, "carrier")
    data = torch.cat(want)
    terminated, truncated = data["next", "terminated"], data["next", "truncated"]
    assert bool((terminated & ~truncated).any()) and bool(truncated.any())
    assert ("dynamics" in data.keys()) == (preset == "paper")
    # the simulator and gymnasium's counters and RNG are where TorchRL's path leaves them
    live, live_r = env_state_dict(env)["workers"][0], env_state_dict(env_r)["workers"][0]
    assert torch.equal(live["sim"]["state"], live_r["sim"]["state"])
    assert live["elapsed_steps"] == live_r["elapsed_steps"] and live["np_random"] == live_r["np_random"]


@pytest.mark.parametrize("direct", [True, False])
def test_a_direct_checkpoint_resumes_into_the_same_batches(direct):
    # what the Trainer saves: the perturbation, the live env and the collector (carrier); resumed with either path
    env, actor = _parts()
    torch.manual_seed(1)
    lean = LeanCollector(env, actor, frames_per_batch=40, init_random_frames=100)
    it = iter(lean)
    for _ in range(12):
        next(it)
    state = {
        "dynamics": dynamics_state_dict(env),
        "env": env_state_dict(env),
        "collector": lean.state_dict(),
        "rng": torch.get_rng_state(),
    }
    tail = [next(it) for _ in range(30)]
    env2, actor2 = _parts(seed=11)  # another seed: everything comes from the checkpoint
    actor2.load_state_dict(actor.state_dict())
    load_dynamics_state_dict(env2, state["dynamics"])
    load_env_state_dict(env2, state["env"])
    resumed = LeanCollector(env2, actor2, frames_per_batch=40, init_random_frames=100, direct=direct)
    resumed.load_state_dict(state["collector"])
    torch.set_rng_state(state["rng"])
    for k, (a, b) in enumerate(zip(_collect(resumed, 30), tail)):
        _assert_same(a, b, f"batch {k}")
    _assert_same(resumed._td, lean._td, "carrier")


def test_humanoid_batches_equal_torchrls():
    env, actor = _parts("Humanoid-v5", max_episode_steps=20)
    torch.manual_seed(1)
    lean = LeanCollector(env, actor, frames_per_batch=40, init_random_frames=80)
    assert lean.direct
    got = _collect(lean, 6)
    env_r, actor_r = _parts("Humanoid-v5", max_episode_steps=20)
    torch.manual_seed(1)
    want, carrier = _reference(env_r, actor_r, 6, 40, 80)
    for k, (a, b) in enumerate(zip(got, want)):
        _assert_same(a, b, f"batch {k}")
    _assert_same(lean._td, carrier, "carrier")
    assert bool(torch.cat(want)["next", "done"].any())


def test_an_unknown_transform_falls_back_and_direct_true_names_it():
    env, actor = _parts()
    env.append_transform(RewardScaling(loc=0.0, scale=2.0))
    assert direct_stepper(env) is None
    lean = LeanCollector(env, actor, frames_per_batch=20, init_random_frames=10)
    assert not lean.direct
    batch = _collect(lean, 2)[1]
    assert batch["next", "reward"].shape == (20, 1)
    with pytest.raises(AdaRLValueError, match="RewardScaling at position 4 is not supported; allowed: .*DoubleToFloat"):
        LeanCollector(env, actor, frames_per_batch=20, direct=True)
    with pytest.raises(AdaRLValueError, match=r"direct must be one of \('auto', True, False\), got 'yes'"):
        LeanCollector(env, actor, frames_per_batch=20, direct="yes")
    plain, actor = _parts()
    assert not LeanCollector(plain, actor, frames_per_batch=20, direct=False).direct


def test_a_carrier_with_an_unknown_entry_is_continued_through_torchrl():
    # TorchRL carries a carrier's extra entries into the frames; the direct path does not know them, so it steps
    # that batch through TorchRL (and directly again once the episode's carrier is the env's own)
    env, actor = _parts()
    lean = LeanCollector(env, actor, frames_per_batch=20, init_random_frames=100)
    lean._td = env.reset()
    lean._td.set("extra", torch.zeros(2))
    batch = _collect(lean, 1)[0]
    assert "extra" in batch.keys() and ("next", "observation") in batch.keys(True)
