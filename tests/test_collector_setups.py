"""Rank events and the warm start in each collector set-up a user would try (issue 22).

Each set-up is a row of the "Supported collectors" table of docs/rank-adapter.md; ``ROWS`` maps the row's first
cell to the test that exercises it, and ``test_doc_table_lists_exactly_the_tested_setups`` checks that the table
and the tests agree. The policy is a deterministic actor so that every stored or collected action can be recomputed:
after an event, the actions a collector takes must be the truncated actor's (not random, not the old policy's).
"""

from __future__ import annotations

import copy
import re
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import GymEnv, SerialEnv, StepCounter, TransformedEnv
from torchrl.modules import Actor, ValueOperator
from torchrl.objectives import TD3Loss, ValueEstimators

from adarl.core.adapter import RankAdapter
from adarl.core.collector_rebuild import CollectorRebuild
from adarl.core.lowrank import low_rank_mlp
from adarl.core.rank import FixedRank
from adarl.core.warmstart import ReplayWarmStart
from adarl.errors import AdaRLValueError

warnings.filterwarnings("ignore", category=UserWarning)
DOC = Path(__file__).resolve().parents[1] / "docs" / "rank-adapter.md"
FPB = 16  # frames per batch

#: first cell of each row of docs/rank-adapter.md's "Supported collectors" table -> the test exercising it
ROWS = {
    "`Collector(env, actor)`, the loop extends the buffer": "test_collector_running_the_actor",
    "`Collector(env, actor, replay_buffer=rb, init_random_frames=N)`": "test_collector_writing_into_the_buffer",
    "`Collector(SerialEnv(n, make_env), actor, replay_buffer=rb)`, several envs": "test_collector_over_several_envs",
    "`Collector(env, copy.deepcopy(actor))`, a policy copy": "test_collector_running_a_policy_copy",
    "`MultiSyncCollector([make_env] * n, actor)`, worker processes": "test_process_collector",
    "`(env, actor)` pair (warm start only)": "test_env_policy_pair",
    "`LeanCollector(env, actor)`, adarl's (a run's collector for one env and a TanhNormal actor)": (
        "test_lean_collector_of_a_run"
    ),
}


def make_env():
    return TransformedEnv(GymEnv("Pendulum-v1"), StepCounter())


class QNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.mlp = low_rank_mlp(4, 1, (16, 16))

    def forward(self, observation, action):
        return self.mlp(torch.cat([observation, action], -1))


def make_agent(env):
    """A deterministic low-rank actor and a TD3 loss holding it (the actor's own Parameters are the loss's)."""
    torch.manual_seed(0)
    spec = env.action_spec_unbatched
    actor = Actor(low_rank_mlp(3, 1, (16, 16)), in_keys=["observation"], spec=spec)
    loss = TD3Loss(actor, ValueOperator(QNet(), in_keys=["observation", "action"]), action_spec=spec)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    return actor, loss, torch.optim.Adam(loss.parameters(), lr=1e-3)


def train_step(loss, opt, rb):
    """One TD3 step on a batch of the buffer: the biases move, so a stale or hybrid policy would show."""
    batch = rb.sample(32).reshape(-1).exclude("collector")
    out = loss(batch)
    opt.zero_grad()
    (out["loss_actor"] + out["loss_qvalue"]).backward()
    opt.step()


def assert_policy_actions(actor, data):
    """Every action in ``data`` is what ``actor`` takes at that observation (so: not random, not an old policy)."""
    data = data.reshape(-1)
    with torch.no_grad():
        expected = actor(data.select("observation").clone())["action"]
    torch.testing.assert_close(data["action"], expected)


def actor_rank(actor) -> int:
    return int(actor.module[2].w1.shape[-1])  # the 16 -> 16 hidden layer (full rank 16)


def stored(rb):
    return rb[: len(rb)]


# --------------------------------------------------------------------------------------------------------------


def test_doc_table_lists_exactly_the_tested_setups():
    text = DOC.read_text(encoding="utf-8")
    section = text.split("## Supported collectors", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `") or line.startswith("| (")]
    cells = [re.split(r"(?<!\\)\|", row)[1].strip() for row in rows]
    assert cells == list(ROWS), "docs/rank-adapter.md 'Supported collectors' must list exactly the tested set-ups"
    for name in ROWS.values():
        assert callable(globals().get(name)), name


def test_collector_running_the_actor():
    env = make_env()
    actor, loss, opt = make_agent(env)
    collector = Collector(env, actor, frames_per_batch=FPB, total_frames=-1, init_random_frames=2 * FPB)
    assert collector.policy is actor
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    warm = ReplayWarmStart(rb, collector, frames=40)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    for i, batch in enumerate(collector):
        if i >= 2:
            assert_policy_actions(actor, batch)  # after the random phase: the actor's actions, at its current rank
        rb.extend(batch.reshape(-1))
        if i >= 2:
            train_step(loss, opt, rb)
        if i == 3:
            adapter.adapt()
            assert actor_rank(actor) == 2 and warm.records[-1].frames_added == 40 and len(rb) == 40
            assert_policy_actions(actor, stored(rb))  # the refill: the truncated actor's frames
        if i == 5:
            break
    collector.shutdown()


def test_collector_writing_into_the_buffer():
    # TorchRL acts randomly while rb.write_count < init_random_frames; a refill that reset the count sent the loop
    # back to random actions after every event
    env = make_env()
    actor, loss, opt = make_agent(env)
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    collector = Collector(
        env, actor, frames_per_batch=FPB, total_frames=-1, init_random_frames=4 * FPB, replay_buffer=rb
    )
    warm = ReplayWarmStart(rb, collector, frames=2 * FPB)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    for i, _ in enumerate(collector):  # the collector writes each batch into rb and yields None
        if i == 7:  # the first batch after the event: the policy's, not the random phase's
            assert_policy_actions(actor, rb[len(rb) - FPB : len(rb)])
            assert actor_rank(actor) == 2
            break
        if i >= 5:
            train_step(loss, opt, rb)
        if i == 6:
            adapter.adapt()
            assert warm.records[-1].emptied and len(rb) == 2 * FPB
            assert_policy_actions(actor, stored(rb))
            assert rb.write_count >= 4 * FPB  # the count of frames written so far survives the refill
    collector.shutdown()


def test_collector_over_several_envs():
    env = SerialEnv(2, make_env)
    actor, loss, opt = make_agent(env)
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    collector = Collector(env, actor, frames_per_batch=FPB, total_frames=-1, replay_buffer=rb)
    warm = ReplayWarmStart(rb, collector, frames=2 * FPB)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    for i, _ in enumerate(collector):
        if i == 3:
            assert_policy_actions(actor, stored(rb)[-2:])  # the batch after the event
            break
        train_step(loss, opt, rb)
        if i == 2:
            adapter.adapt()
            # the buffer holds one entry of FPB / 2 frames per env and batch: the warm start counts frames
            rec = warm.records[-1]
            assert rec.frames_added == 2 * FPB and stored(rb).numel() == 2 * FPB and len(rb) == 4
            assert_policy_actions(actor, stored(rb))
    collector.shutdown()


def test_collector_running_a_policy_copy():
    env = make_env()
    actor, loss, opt = make_agent(env)
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    copier = Collector(env, copy.deepcopy(actor), frames_per_batch=FPB, total_frames=-1)
    rb.extend(copier.rollout().reshape(-1))
    warm = ReplayWarmStart(rb, copier, frames=FPB)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    # the copy would refill the buffer with the pre-truncation policy: refused before anything changes
    with pytest.raises(AdaRLValueError, match="copy of the actor"):
        adapter.adapt()
    assert actor_rank(actor) == 16 and len(rb) == FPB and adapter.history == []
    copier.shutdown()
    # the training loop with a copying collector: rebuilt after each event, so the copy has the new ranks
    collector = CollectorRebuild(
        lambda: Collector(env, copy.deepcopy(actor), frames_per_batch=FPB, total_frames=-1), total_frames=6 * FPB
    )
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[collector])
    batches = []
    for i, batch in enumerate(collector):
        assert_policy_actions(actor, batch)  # the copy made after the event acts as the trainer's actor does
        rb.extend(batch.reshape(-1))
        train_step(loss, opt, rb)
        if i == 2:
            adapter.adapt()  # rebuilds the collector: a fresh copy at the new ranks
        else:
            collector.update_policy_weights_(TensorDict.from_module(actor))  # between events: synced as usual
        batches.append(batch)
    assert len(batches) == 6 and collector.rebuilds == 1 and collector.frames == 6 * FPB
    collector.shutdown()


def test_env_policy_pair():
    env = make_env()
    actor, loss, opt = make_agent(env)
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    rb.extend(env.rollout(20, policy=actor, break_when_any_done=False))
    warm = ReplayWarmStart(rb, (env, actor), frames=30)
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, scope="actor", on_truncate=[warm])
    adapter.adapt()
    assert warm.records[-1].frames_added == 30 and len(rb) == 30 and rb.write_count == 50
    assert_policy_actions(actor, stored(rb))
    stale = ReplayWarmStart(rb, (env, copy.deepcopy(actor)), frames=30)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[stale])
    with pytest.raises(AdaRLValueError, match="copy of the actor"):
        adapter.adapt()
    assert actor_rank(actor) == 3 and len(rb) == 30


def test_factors_in_shared_memory_need_a_collector_rebuild():
    # what a process collector does to the policy's parameters on CPU; the check is on the tensors, so it holds for
    # every collector that maps them (MultiSyncCollector, MultiAsyncCollector, AsyncCollector, ...)
    env = make_env()
    actor, loss, opt = make_agent(env)
    for p in actor.parameters():
        p.share_memory_()
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor")
    with pytest.raises(AdaRLValueError, match="shared memory.*Nothing was changed.*CollectorRebuild"):
        adapter.adapt()
    assert actor_rank(actor) == 16 and adapter.history == []
    rebuilt = []

    class Rebuild:  # anything that declares it rebuilds the collector
        rebuilds_collector = True

        def __call__(self, event):
            rebuilt.append(event.index)

    RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[Rebuild()]).adapt()
    assert actor_rank(actor) == 2 and rebuilt == [0]


def test_warm_start_refuses_sources_that_cannot_collect_with_the_actor():
    env = make_env()
    actor, _, _ = make_agent(env)
    rb = ReplayBuffer(storage=LazyTensorStorage(50))

    class FakeMulti:  # what a MultiSyncCollector offers: reset() and iteration, no rollout()
        def reset(self):
            pass

    with pytest.raises(AdaRLValueError, match=r"\(env, actor\) pair"):
        ReplayWarmStart(rb, FakeMulti(), frames=4)
    rebuild = CollectorRebuild(lambda: Collector(env, actor, frames_per_batch=FPB, total_frames=-1))
    with pytest.raises(AdaRLValueError, match=r"\(env, actor\) pair"):
        ReplayWarmStart(rb, rebuild, frames=4)
    rebuild.shutdown()
    with pytest.raises(AdaRLValueError, match="make_collector"):
        CollectorRebuild("MultiSyncCollector")
    with pytest.raises(AdaRLValueError, match="TorchRL collector"):
        CollectorRebuild(lambda: None)
    with pytest.raises(AdaRLValueError, match="total_frames"):
        CollectorRebuild(lambda: rebuild.collector, total_frames=0)


def _make_pendulum():  # module level: picklable for the worker processes
    return GymEnv("Pendulum-v1")


@pytest.mark.slow
def test_process_collector():
    from torchrl.collectors import MultiSyncCollector

    env = make_env()
    actor, loss, opt = make_agent(env)

    def make_collector():
        return MultiSyncCollector([_make_pendulum], actor, frames_per_batch=FPB, total_frames=-1)  # one worker: fast

    collector = CollectorRebuild(make_collector)
    assert all(p.is_shared() for p in actor.parameters())  # the workers map the trainer's tensors
    rb = ReplayBuffer(storage=LazyTensorStorage(500))
    pair = _make_pendulum()  # the same env layout as the workers' (one data source per buffer)
    warm = ReplayWarmStart(rb, (pair, actor), frames=FPB)  # a process collector cannot be the warm start's source
    # without the rebuild, an event would leave the workers with the old factors and the new biases: refused
    bare = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    try:
        for i, batch in enumerate(collector):
            assert_policy_actions(actor, batch)  # the workers act exactly as the trainer's actor
            rb.extend(batch.reshape(-1).exclude("collector"))
            train_step(loss, opt, rb)
            if i == 1:
                with pytest.raises(AdaRLValueError, match="shared memory"):
                    bare.adapt()
                assert actor_rank(actor) == 16
                adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[collector, warm])
                adapter.adapt()
                assert actor_rank(actor) == 2 and collector.rebuilds == 1 and warm.records[-1].frames_added == FPB
                assert all(p.is_shared() for p in actor.parameters())  # the new workers map the new tensors
            if i == 3:
                break
        collector.update_policy_weights_()  # in place, same shapes: works again
        with pytest.raises(AdaRLValueError, match=r"\(env, actor\) pair"):
            ReplayWarmStart(rb, collector.collector, frames=FPB)
    finally:
        collector.shutdown()
    assert i == 3


def test_lean_collector_of_a_run():
    """adarl's LeanCollector: after an event the warm start collects through it (``rollout()``) with the truncated
    actor, and the buffer gets what an ``(env, actor)`` pair's ``env.rollout`` gives, bit for bit, from the same
    seeds (the random phase off while it collects)."""
    from adarl.fast.collector import LeanCollector
    from adarl.runtime.builders.sac import build_sac_components
    from adarl.runtime.config import load_recipe

    overrides = [
        "collector.total_frames=2000",
        "collector.init_random_frames=100",
        "collector.frames_per_batch=50",
        "replay.size=2000",
        "replay.warm_start.frames=120",
    ]

    def run(pair: bool):
        torch.manual_seed(0)
        c = build_sac_components(load_recipe("quickstart", overrides))
        assert isinstance(c.collector, LeanCollector) and c.warm_start.source is c.collector
        if pair:
            c.warm_start.source = (c.env, c.modules.actor)  # the path the lean collector's rollout() replaced
        batch = next(iter(c.collector))
        c.replay_buffer.extend(batch.reshape(-1))
        torch.manual_seed(1)
        event = c.adapter.adapt()
        return event, c

    event, lean = run(pair=False)
    _, ref = run(pair=True)
    assert event.changed and len(lean.replay_buffer) == len(ref.replay_buffer) == 120
    assert lean.collector.frames == 50 and lean.collector.init_random_frames == 100  # the iteration's, untouched
    got, want = stored(lean.replay_buffer), stored(ref.replay_buffer)
    for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done")):
        assert torch.equal(got.get(key), want.get(key)), key
