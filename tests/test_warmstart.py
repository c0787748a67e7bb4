"""ReplayWarmStart: refill / prefill / keep after a rank event, from a Collector or an (env, policy) pair."""

import warnings

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import GymEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators

from adarl.core.adapter import RankAdapter
from adarl.core.lowrank import low_rank_mlp
from adarl.core.rank import FixedRank
from adarl.core.warmstart import ReplayWarmStart
from adarl.errors import AdaRLValueError

warnings.filterwarnings("ignore", category=UserWarning)


def make_env():
    return TransformedEnv(GymEnv("Pendulum-v1"), StepCounter())


def make_actor(env):
    torch.manual_seed(0)
    net = nn.Sequential(low_rank_mlp(3, 2, (16, 16)), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        spec=env.action_spec,
    )


def filled_buffer(env, policy, n=40):
    rb = ReplayBuffer(storage=LazyTensorStorage(200))
    rb.extend(env.rollout(n, policy=policy, break_when_any_done=False).reshape(-1))
    return rb


def stored(rb):
    return rb[: len(rb)]


def test_refill_from_collector_with_the_new_policy():
    env = make_env()
    actor = make_actor(env)

    class Q(nn.Module):  # Q(obs, act) for SACLoss
        def __init__(self):
            super().__init__()
            self.mlp = low_rank_mlp(4, 1, (16, 16))

        def forward(self, observation, action):
            return self.mlp(torch.cat([observation, action], -1))

    qv = ValueOperator(Q(), in_keys=["observation", "action"])
    loss = SACLoss(actor, qv, action_spec=env.action_spec)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    SoftUpdate(loss, eps=0.99)
    opt = torch.optim.Adam(loss.parameters())
    rb = ReplayBuffer(storage=LazyTensorStorage(500), batch_size=8)
    # a collector that writes into the buffer, with a random-action phase gated on rb.write_count (which empty()
    # resets: without ReplayWarmStart switching it off, the refill would be random actions)
    collector = Collector(
        env,
        actor,
        frames_per_batch=16,
        total_frames=-1,
        init_random_frames=16,
        replay_buffer=rb,
        exploration_type=ExplorationType.DETERMINISTIC,  # so stored actions can be recomputed
    )
    collector.init_random_frames = 0  # policy frames first (the storage layout then has the policy's keys)
    for _ in collector:
        if len(rb) >= 48:
            break
    collector.init_random_frames = 16
    size = len(rb)
    warm = ReplayWarmStart(rb, collector, frames=40, mode="refill")
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor", on_truncate=[warm])
    event = adapter.adapt()
    (rec,) = warm.records
    assert rec.step == event.step and rec.emptied and rec.size_before == size
    assert rec.frames_added == 40 and rec.size_after == len(rb) == 40  # the last batch trimmed
    data = stored(rb)
    assert int(data["step_count"][0]) == 0  # a reset first: fresh episodes (and fresh dynamics)
    # every frame comes from the truncated policy, none from the random-action phase
    assert collector.policy is actor and actor.module[0].module[0][0].w1.shape[-1] == 2
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        actions = actor(data.select("observation").clone())["action"]
    torch.testing.assert_close(data["action"], actions)
    assert collector.init_random_frames == 16  # restored
    collector.shutdown()


def test_collector_batches_are_trimmed_when_extended_here():
    env = make_env()
    actor = make_actor(env)
    collector = Collector(env, actor, frames_per_batch=16, total_frames=-1)
    rb = ReplayBuffer(storage=LazyTensorStorage(200))
    rb.extend(collector.rollout().reshape(-1))  # one source per buffer: the storage layout is fixed at first write
    rec = ReplayWarmStart(rb, collector, frames=20, mode="prefill")()
    assert (rec.size_before, rec.frames_added, rec.size_after, rec.emptied) == (16, 20, 36, False)
    collector.shutdown()


@pytest.mark.parametrize(
    "mode, expected",
    [("refill", (25, 25, True)), ("prefill", (25, 65, False)), ("keep", (0, 40, False))],
)
def test_modes_with_env_policy_pair(mode, expected):
    env = make_env()
    actor = make_actor(env)
    rb = filled_buffer(env, actor, 40)
    first_before = stored(rb)["observation"][0].clone()
    warm = ReplayWarmStart(rb, (env, actor), frames=25 if mode != "keep" else 0, mode=mode)
    rec = warm()
    assert (rec.frames_added, rec.size_after, rec.emptied) == expected
    assert rec.size_before == 40 and len(rb) == rec.size_after and rec.mode == mode and rec.step is None
    data = stored(rb)
    if mode == "refill":
        assert int(data["step_count"][0]) == 0
    else:
        assert torch.equal(data["observation"][0], first_before)  # old frames kept
    if mode == "prefill":
        assert int(data["step_count"][40]) == 0  # new frames start with a reset
    assert warm.state_dict()["records"][0]["mode"] == mode


def test_validation():
    env = make_env()
    actor = make_actor(env)
    rb = filled_buffer(env, actor, 4)
    with pytest.raises(AdaRLValueError, match="mode"):
        ReplayWarmStart(rb, (env, actor), frames=4, mode="restart")
    with pytest.raises(AdaRLValueError, match="frames"):
        ReplayWarmStart(rb, (env, actor), frames=0, mode="refill")
    with pytest.raises(AdaRLValueError, match="source"):
        ReplayWarmStart(rb, actor, frames=4)
    with pytest.raises(AdaRLValueError, match="replay_buffer"):
        ReplayWarmStart([], (env, actor), frames=4)
