"""RankAdapter beyond SAC: TD3Loss, ClipPPOLoss (functional and not), DiscreteSACLoss, and the Trainer hook."""

import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.modules import Actor, OneHotCategorical, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss, DiscreteSACLoss, SoftUpdate, TD3Loss, ValueEstimators

from adarl.adapter import RankAdapter, resize_to_ranks
from adarl.lowrank import low_rank_mlp
from adarl.rank import EnergyRule, FixedRank, PolicyFitRule

warnings.filterwarnings("ignore", category=UserWarning)
OBS, ACT, B = 5, 2, 16


class QNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.mlp = low_rank_mlp(OBS + ACT, 1, (16, 16))

    def forward(self, observation, action):
        return self.mlp(torch.cat([observation, action], -1))


def transition_batch(seed=0, action=None):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(B, OBS, generator=g),
            "action": torch.rand(B, ACT, generator=g) * 1.8 - 0.9 if action is None else action,
            "next": {
                "observation": torch.randn(B, OBS, generator=g),
                "reward": torch.randn(B, 1, generator=g),
                "done": torch.zeros(B, 1, dtype=torch.bool),
                "terminated": torch.zeros(B, 1, dtype=torch.bool),
            },
        },
        [B],
    )


def run(loss, opt, adapter, steps, batch_fn, updater=None):
    """Optimise, keeping the last graph alive across events; check finiteness and that factors move."""
    events = []
    for i in range(steps):
        out = loss(batch_fn(i))
        value = sum(v for k, v in out.items() if k.startswith("loss_"))
        assert torch.isfinite(value)
        opt.zero_grad()
        value.backward()
        before = [s.w1.detach().clone() for s in adapter.sites]
        opt.step()
        for s, b in zip(adapter.sites, before):
            assert not torch.equal(s.w1, b), s.path  # the optimiser steps the (new) tensors
            assert opt.state[s.w1]["exp_avg"].shape == s.w1.shape
        if updater is not None:
            updater.step()
        ev = adapter.step()
        if ev is not None:
            events.append(ev)
    return events


def check_targets(loss, names):
    for name in names:
        online = getattr(loss, f"{name}_params")
        target = loss._modules[f"target_{name}_params"]
        for k in online.keys(True, True):
            assert online.get(k).shape == target.get(k).shape, (name, k)


def test_td3_loss():
    torch.manual_seed(0)
    actor = Actor(low_rank_mlp(OBS, ACT, (16, 16)), in_keys=["observation"])
    qv = ValueOperator(QNet(), in_keys=["observation", "action"])
    loss = TD3Loss(actor, qv, bounds=(-1.0, 1.0), loss_function="l2")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    updater = SoftUpdate(loss, eps=0.9)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3, fused=True)
    adapter = RankAdapter(loss, opt, EnergyRule(0.98), interval=3, target_mode="project")
    roles = adapter.layers
    assert sorted(roles.values()) == ["actor", "actor", "critic", "critic"]
    events = run(loss, opt, adapter, 10, transition_batch, updater)
    assert len(events) == 3 and all(e.changed for e in events)
    check_targets(loss, ["actor_network", "qvalue_network"])  # TD3 has a target actor too
    # the detached Q params the actor loss caches (created by the forward just before the last event) are rebuilt
    cached = loss._cached_detach_qvalue_network_params.get(("module", "mlp", "0", "w1"))
    assert cached.shape == (2, 16, adapter.ranks["qvalue_network.module.mlp.0"])
    stacked = loss._cached_stack_actor_params.get(("module", "0", "w1"))
    assert stacked.shape == (2, 16, adapter.ranks["actor_network.module.0"])
    recs = [r for e in events for r in e.layers if r.network == "actor"]
    assert all(r.target in ("project", None) or r.target.startswith("sync (fallback") for r in recs)
    # the deterministic actor (what a collector runs) is the trained one
    td = transition_batch(5).select("observation")
    with loss.actor_network_params.to_module(loss.actor_network):
        a = loss.actor_network(td.clone())["action"]
    torch.testing.assert_close(actor(td.clone())["action"], a)
    updater.step()


def test_td3_policy_fit_compares_actions():
    torch.manual_seed(1)
    actor = Actor(low_rank_mlp(OBS, ACT, (16, 16)), in_keys=["observation"])
    qv = ValueOperator(QNet(), in_keys=["observation", "action"])
    loss = TD3Loss(actor, qv, bounds=(-1.0, 1.0))
    opt = torch.optim.Adam(loss.parameters())
    adapter = RankAdapter(loss, opt, PolicyFitRule(lam=1e-3), interval=1, fit_data=lambda: transition_batch(2))
    event = adapter.adapt()
    assert {r.network for r in event.layers} == {"actor", "critic"}
    assert any(r.changed for r in event.layers)


def make_ppo(functional=True, delay_actor=False):
    torch.manual_seed(0)
    net = nn.Sequential(low_rank_mlp(OBS, 2 * ACT, (16, 16)), NormalParamExtractor())
    actor = ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        return_log_prob=True,
    )
    critic = ValueOperator(low_rank_mlp(OBS, 1, (16, 16)), in_keys=["observation"])
    loss = ClipPPOLoss(actor, critic, functional=functional, delay_actor=delay_actor)
    return loss, actor, critic


def ppo_batch_fn(loss):
    def fn(i):
        g = torch.Generator().manual_seed(i)
        return TensorDict(
            {
                "observation": torch.randn(B, OBS, generator=g),
                "action": torch.rand(B, ACT, generator=g) * 1.8 - 0.9,
                loss.tensor_keys.sample_log_prob: torch.randn(B, generator=g),
                "advantage": torch.randn(B, 1, generator=g),
                "value_target": torch.randn(B, 1, generator=g),
            },
            [B],
        )

    return fn


@pytest.mark.parametrize("functional", [True, False])
def test_clip_ppo_loss(functional):
    loss, actor, critic = make_ppo(functional)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    adapter = RankAdapter(loss, opt, EnergyRule(0.98), interval=2)
    assert sorted(adapter.layers.items()) == [
        ("actor_network.module.0.module.0.0", "actor"),
        ("actor_network.module.0.module.0.2", "actor"),
        ("critic_network.module.0", "critic"),
        ("critic_network.module.2", "critic"),
    ]
    events = run(loss, opt, adapter, 6, ppo_batch_fn(loss))
    assert len(events) == 3 and all(e.changed for e in events)
    # the critic (and actor) modules the user holds are the trained ones
    assert critic.module[0].w1.shape[-1] == adapter.ranks["critic_network.module.0"]
    # a fresh loss takes the truncated state_dict after resize_to_ranks (ranks read from the w2 shapes)
    fresh, _, _ = make_ppo(functional)
    assert set(resize_to_ranks(fresh, loss.state_dict())) == set(adapter.ranks)
    fresh.load_state_dict(loss.state_dict())
    if functional:
        assert critic.module[0].w1 is loss.critic_network_params.get(("module", "0", "w1"))
        loss._cached_critic_network_params_detached  # cached (used when the loss computes advantages itself)
        RankAdapter(loss, opt, FixedRank(1), interval=1, scope="critic").adapt()
        cached = loss._cached_critic_network_params_detached.get(("module", "0", "w1"))
        assert cached.shape == critic.module[0].w1.shape == (16, 1)


def test_clip_ppo_delay_actor_target_and_actor_scope():
    loss, actor, critic = make_ppo(delay_actor=True)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, scope="actor")
    adapter.adapt()
    check_targets(loss, ["actor_network"])
    assert critic.module[0].w1.shape[-1] == 5  # critic untouched
    run(loss, opt, adapter, 1, ppo_batch_fn(loss))


def test_discrete_sac_loss():
    torch.manual_seed(0)
    n_act = 3
    actor = ProbabilisticActor(
        TensorDictModule(low_rank_mlp(OBS, n_act, (16, 16)), ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
    )
    qv = ValueOperator(low_rank_mlp(OBS, n_act, (16, 16)), in_keys=["observation"], out_keys=["action_value"])
    loss = DiscreteSACLoss(actor, qv, num_actions=n_act, action_space="one-hot")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    updater = SoftUpdate(loss, eps=0.9)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    adapter = RankAdapter(
        loss, opt, PolicyFitRule(lam=1e-3), interval=2, fit_data=lambda: transition_batch(9), min_rank=2
    )

    def batch(i):
        g = torch.Generator().manual_seed(100 + i)
        a = torch.nn.functional.one_hot(torch.randint(n_act, (B,), generator=g), n_act)
        return transition_batch(i, action=a)

    adapter.rule = EnergyRule(0.98)  # first events: ratchet down; last: the policy-fit measurement on logits
    events = run(loss, opt, adapter, 4, batch, updater)
    adapter.rule = PolicyFitRule(lam=1e-3)
    events += run(loss, opt, adapter, 2, batch, updater)
    assert len(events) == 3
    check_targets(loss, ["qvalue_network"])


def test_trainer_hook_registration_and_checkpoint():
    from torchrl.trainers.trainers import TrainerHookBase

    loss, _, _ = make_ppo()
    opt = torch.optim.Adam(loss.parameters())
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=2)
    assert isinstance(adapter, TrainerHookBase)

    class FakeTrainer:  # the two Trainer methods a hook uses
        def __init__(self):
            self.ops, self.modules = [], {}

        def register_op(self, dest, op, **kwargs):
            self.ops.append((dest, op))

        def register_module(self, name, module):
            self.modules[name] = module

    trainer = FakeTrainer()
    adapter.register(trainer)
    assert trainer.modules == {"rank_adapter": adapter}
    (dest, op), = trainer.ops
    assert dest == "post_optim"
    op(), op()  # the Trainer calls post_optim ops without arguments
    assert adapter.step_count == 2 and len(adapter.history) == 1 and set(adapter.ranks.values()) == {2}

    # round trip into a fresh PPO loss
    state = {"loss": loss.state_dict(), "adapter": adapter.state_dict()}
    fresh, _, _ = make_ppo()
    resize_to_ranks(fresh, state["loss"])
    fresh.load_state_dict(state["loss"])
    td = ppo_batch_fn(loss)(0)
    torch.manual_seed(0)
    a = loss(td.clone())
    torch.manual_seed(0)
    b = fresh(td.clone())
    for k in ("loss_objective", "loss_critic"):
        torch.testing.assert_close(a[k], b[k])
