"""LeanCollector: the same actions as TorchRL's ProbabilisticActor, consistent transitions, random phase."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from adarl.errors import AdaRLValueError
from adarl.fast.collector import LeanCollector, _layer_chain, wants_lean
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe

OVR = [
    "collector.total_frames=2000",
    "collector.init_random_frames=10",
    "collector.frames_per_batch=40",
    "replay.size=2000",
]


@pytest.fixture(scope="module")
def comps():
    return build_sac_components(load_recipe("quickstart", OVR))


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


def test_the_layer_chain_computes_the_network_bit_for_bit(comps):
    net = comps.modules.actor.module[0].module
    chain = _layer_chain(net)
    assert chain is not net
    obs = torch.randn(500, 11)
    with torch.no_grad():
        for x in obs:
            loc, scale = net(x.clone())
            loc_c, scale_c = chain(x.clone())
            assert torch.equal(loc, loc_c) and torch.equal(scale, scale_c)
    handle = net[0][2].register_forward_hook(lambda module, args, out: out)
    assert _layer_chain(net) is net  # a hook would be skipped: the network is called as a module
    handle.remove()


@pytest.mark.parametrize("direct", ["auto", False], ids=["direct", "torchrl-step"])
def test_batches_equal_torchrl_collectors(direct):
    """From the same seeds, LeanCollector hands out TorchRL's Collector's batches: every key it writes, bit for bit,
    through the random phase, policy actions, episode ends and resets."""
    from torchrl.collectors import Collector

    from adarl.runtime.builders.common import train_env_factory
    from adarl.runtime.builders.sac import make_sac_modules

    recipe = load_recipe(
        "quickstart", ["collector.total_frames=2000", "collector.init_random_frames=60", "replay.size=2000"]
    )
    factory = train_env_factory(recipe)
    env_lean, env_torchrl = factory(), factory()  # the same seed: the same episodes and dynamics draws
    torch.manual_seed(0)
    actor = make_sac_modules(recipe, env_lean).actor
    lean = LeanCollector(env_lean, actor, frames_per_batch=60, init_random_frames=60, total_frames=240, direct=direct)
    ref = Collector(env_torchrl, actor, frames_per_batch=60, total_frames=240, init_random_frames=60)
    batches = {}
    for name, collector in (("lean", lean), ("torchrl", ref)):
        torch.manual_seed(123)  # the action noise (and the random phase's actions) from the global RNG, as TorchRL
        batches[name] = torch.cat([b.clone() for b in collector])
        collector.shutdown()
    got, want = batches["lean"], batches["torchrl"]
    assert got.shape == want.shape == (240,)
    assert int(got["next", "done"].sum()) >= 2  # episodes ended and were reset inside the window
    keys = set(got.keys(True, True))
    assert keys <= set(want.keys(True, True)) and {"observation", "action", ("next", "reward")} <= keys
    for key in keys:
        assert torch.equal(got.get(key), want.get(key)), key


def test_batches_are_consistent_transitions(comps):
    lean = LeanCollector(comps.env, comps.modules.actor, frames_per_batch=40, init_random_frames=10, total_frames=120)
    batches = list(lean)
    assert [b.shape[0] for b in batches] == [40, 40, 40] and lean.frames == 120
    data = torch.cat(batches)
    for key in (
        "observation",
        "action",
        ("next", "observation"),
        ("next", "reward"),
        ("next", "terminated"),
        ("next", "done"),
        ("next", "episode_reward"),
    ):
        assert key in data.keys(True), key
    done = data["next", "done"].squeeze(-1)
    same = torch.isclose(data["next", "observation"][:-1], data["observation"][1:]).all(-1)
    assert bool(same[~done[:-1]].all())  # s' of a step is s of the next one unless the episode ended
    assert data["action"].abs().max() <= 1.0


def test_trainer_wiring_and_fallbacks():
    comps = build_sac_components(load_recipe("quickstart", OVR + ["collector.lean=false"]))
    assert not isinstance(comps.collector, LeanCollector)
    disc = build_sac_components(
        load_recipe("cartpole_adarl", ["collector.total_frames=1000", "collector.init_random_frames=250"])
    )
    assert not isinstance(disc.collector, LeanCollector)
    with pytest.raises(AdaRLValueError, match="collector.lean"):
        wants_lean(True, disc.env, disc.modules.actor)


def _env_and_actor(seed):
    c = build_sac_components(load_recipe("quickstart", OVR + [f"seed={seed}"]))
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
        build_sac_components(load_recipe("quickstart", OVR + ["collector.overlap=true", "collector.lean=false"]))


# ---------------------------------------------------------------------------------------- overlap: "process"
def _parts(seed):
    from adarl.runtime.builders.common import train_env_factory

    recipe = load_recipe("quickstart", OVR + [f"seed={seed}"])
    c = build_sac_components(recipe)
    return c.env, c.modules.actor, train_env_factory(recipe)


def _run_overlapped(mode, seed=5, batches=12, state_at=None, direct="auto"):
    """Batches of an overlapped collector while the 'updates' change the actor in place between batches."""
    from adarl.envs.state import env_state_dict

    env, actor, factory = _parts(seed)
    torch.manual_seed(0)
    # a short episode cap: several episode ends (and perturbation redraws) inside the batches
    x = LeanCollector(
        env,
        actor,
        frames_per_batch=30,
        init_random_frames=20,
        overlap=mode,
        noise_seed=9,
        env_factory=factory,
        direct=direct,
    )
    assert x.direct == (direct == "auto")
    out, state = [], None
    for k, batch in enumerate(x):
        with torch.no_grad():
            for p in actor.parameters():
                p.add_(0.05 * torch.randn_like(p))
        out.append(batch)
        if k == state_at:
            state = x.state_dict()
        if k == batches - 1:
            break
    x.drain(keep=True)  # the caller's env is where the last prefetched batch left it
    live = env_state_dict(env)
    x.shutdown()
    return out, live, state, x


def test_process_overlap_hands_out_the_thread_modes_batches_and_env_state():
    # the thread steps through TorchRL (direct=False), the worker process directly (adarl.fast.direct_env)
    thread, live_t, state_t, _ = _run_overlapped("thread", state_at=6, direct=False)
    proc, live_p, state_p, x = _run_overlapped("process", state_at=6)
    assert x._worker is None  # shutdown stopped the worker
    assert len(thread) == len(proc) == 12
    done = torch.cat([b.get(("next", "done")) for b in proc]).sum()
    assert done >= 1  # the batches cross episode ends
    for k, (a, b) in enumerate(zip(thread, proc)):
        assert list(a.keys(True, True)) == list(b.keys(True, True))
        for key in a.keys(True, True):
            assert torch.equal(a.get(key), b.get(key)), (k, key)
    # the caller's env was given the worker's final state: bit-identical simulator and gymnasium state
    assert torch.equal(live_t["workers"][0]["sim"]["state"], live_p["workers"][0]["sim"]["state"])
    assert live_t["workers"][0]["np_random"] == live_p["workers"][0]["np_random"]
    # a checkpoint taken while the worker collects holds the finished prefetched batch, as in the thread mode
    assert torch.equal(state_t["prefetched"]["action"], state_p["prefetched"]["action"])
    assert torch.equal(state_t["noise_rng"], state_p["noise_rng"])


def test_process_overlap_resumes_from_a_state_dict():
    # what the Trainer checkpoints: the collector's state (which finishes the prefetched batch first), then the
    # env's live state, which the worker's final state was loaded into
    from adarl.envs import dynamics_state_dict, load_dynamics_state_dict
    from adarl.envs.state import env_state_dict, load_env_state_dict

    env, actor, factory = _parts(6)
    x = LeanCollector(
        env, actor, frames_per_batch=20, init_random_frames=0, overlap="process", noise_seed=1, env_factory=factory
    )
    it = iter(x)
    next(it)  # batch 1 handed over, batch 2 being collected by the worker
    state = x.state_dict()
    assert state["prefetched"] is not None and x.frames == 40
    dynamics, live = dynamics_state_dict(env), env_state_dict(env)
    batch2, batch3 = next(it), next(it)
    x.shutdown()
    env2, actor2, factory2 = _parts(6)
    actor2.load_state_dict(actor.state_dict())  # the policy batch 3 was collected with (after batch 2's prefetch)
    load_dynamics_state_dict(env2, dynamics)
    load_env_state_dict(env2, live)
    y = LeanCollector(
        env2, actor2, frames_per_batch=20, init_random_frames=0, overlap="process", noise_seed=1, env_factory=factory2
    )
    y.load_state_dict(state)
    it = iter(y)
    assert torch.equal(next(it).get("action"), batch2.get("action"))
    b3 = next(it)
    for key in ("observation", "action", ("next", "reward")):
        assert torch.equal(b3.get(key), batch3.get(key)), key
    y.shutdown()


def test_overlap_rejects_bad_values_and_a_missing_env_factory(comps):
    with pytest.raises(AdaRLValueError, match="overlap must be one of .*'thread', 'process'"):
        LeanCollector(comps.env, comps.modules.actor, frames_per_batch=10, overlap="threads")
    with pytest.raises(AdaRLValueError, match="env_factory"):
        LeanCollector(comps.env, comps.modules.actor, frames_per_batch=10, overlap="process")
    from adarl.errors import RecipeError

    with pytest.raises(RecipeError, match="collector.overlap"):
        load_recipe("quickstart", OVR + ["collector.overlap=processes"])
    assert load_recipe("quickstart", OVR + ["collector.overlap=process"]).collector.overlap == "process"
    assert load_recipe("quickstart", OVR + ["collector.overlap=true"]).collector.overlap is True


def test_a_failing_worker_raises_with_its_traceback(comps):
    import functools

    from adarl.envs import make_env

    x = LeanCollector(
        comps.env,
        comps.modules.actor,
        frames_per_batch=10,
        init_random_frames=0,
        overlap="process",
        env_factory=functools.partial(make_env, "NoSuchEnv-v9"),
    )
    it = iter(x)
    next(it)  # collected here; the worker (which cannot build its env) gets the next batch
    with pytest.raises(RuntimeError, match="collector worker process failed(.|\n)*NoSuchEnv-v9"):
        next(it)
    x.shutdown()


_ORPHAN = """
import os, sys, time
from adarl.runtime.config import load_recipe
from adarl.runtime.builders.sac import build_sac_components

if __name__ == "__main__":
    c = build_sac_components(load_recipe("quickstart", sys.argv[1:] + ["collector.overlap=process",
                                                                   "collector.init_random_frames=0"]))
    it = iter(c.collector)
    next(it)
    print(c.collector._worker.proc.pid, flush=True)
    time.sleep(600)
"""


def test_the_worker_exits_when_its_trainer_is_killed(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "orphan.py"
    script.write_text(_ORPHAN)
    proc = subprocess.Popen([sys.executable, str(script), *OVR], stdout=subprocess.PIPE, text=True)
    pid = int(proc.stdout.readline())
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    end = time.monotonic() + 30
    while time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return  # gone (and reaped by init)
        try:  # a zombie that init has not reaped yet counts as gone
            if open(f"/proc/{pid}/stat").read().split()[2] == "Z":
                return
        except FileNotFoundError:
            return
        time.sleep(0.2)
    os.kill(pid, signal.SIGKILL)
    raise AssertionError("the collector worker outlived its killed trainer")


def test_warm_start_rollout_equals_torchrls_env_rollout_and_leaves_the_iteration_alone():
    """The warm start after a rank event collects through LeanCollector.rollout() (about 3x faster a frame than
    TorchRL's env.rollout, which it replaces): from the same seeds the buffer gets the frames env.rollout with the
    actor gave, bit for bit, exactly ``frames`` of them, from the policy (the random phase off while it collects),
    and the collector's frame count and random phase are as before."""
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from adarl.core.warmstart import ReplayWarmStart
    from adarl.runtime.builders.common import train_env_factory
    from adarl.runtime.builders.sac import make_sac_modules

    recipe = load_recipe("quickstart", OVR)
    factory = train_env_factory(recipe)
    env_lean, env_torchrl = factory(), factory()
    torch.manual_seed(0)
    actor = make_sac_modules(recipe, env_lean).actor
    lean = LeanCollector(env_lean, actor, frames_per_batch=40, init_random_frames=1000)
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(500))
    warm = ReplayWarmStart(buffer, lean, frames=100)
    torch.manual_seed(5)
    record = warm()
    assert record.frames_added == 100 and len(buffer) == 100
    assert lean.frames == 0 and lean.init_random_frames == 1000
    torch.manual_seed(5)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        want = env_torchrl.rollout(100, policy=actor, auto_reset=True, break_when_any_done=False)
    got = buffer[:100]
    assert int(want["next", "done"].sum()) >= 1  # an episode ended and was reset inside the warm start
    for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done")):
        assert torch.equal(got.get(key), want.get(key)), key


def test_the_trainers_warm_start_collects_through_the_lean_collector(comps):
    assert comps.warm_start is not None and comps.warm_start.source is comps.collector
