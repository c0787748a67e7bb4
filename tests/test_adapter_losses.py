"""RankAdapter beyond SAC: every stock TorchRL loss (tested through a truncation, or refused by name), the Trainer hook.

The truncation test runs every loss of ``adarl.core.adapter.SUPPORTED_LOSSES``; another test checks that every loss
class TorchRL exports is in that registry or in ``UNSUPPORTED_LOSSES``, and that docs/rank-adapter.md's table is them.
"""

import inspect
import re
import warnings
from pathlib import Path

import pytest
import torch
import torchrl.objectives as objectives
import torchrl.objectives.multiagent as multiagent_objectives
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded, OneHot
from torchrl.modules import (
    Actor,
    DistributionalQValueActor,
    OneHotCategorical,
    ProbabilisticActor,
    QValueActor,
    TanhNormal,
    ValueOperator,
)
from torchrl.objectives import ClipPPOLoss, DiscreteSACLoss, SoftUpdate, TD3Loss, ValueEstimators

from adarl.core.adapter import SUPPORTED_LOSSES, UNSUPPORTED_LOSSES, RankAdapter, check_loss_supported, resize_to_ranks
from adarl.core.lowrank import low_rank_mlp
from adarl.core.rank import EnergyRule, FixedRank, PolicyFitRule
from adarl.errors import AdaRLValueError

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
        _ = loss._cached_critic_network_params_detached  # cached (used when the loss computes advantages itself)
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
    ((dest, op),) = trainer.ops
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


# --------------------------------------------------------------------------------------------------------------
# Every stock TorchRL loss: tested through a truncation (SUPPORTED_LOSSES) or refused by name (UNSUPPORTED_LOSSES)
# --------------------------------------------------------------------------------------------------------------

N_ACT, ATOMS = 3, 5
SPEC = Bounded(-torch.ones(ACT), torch.ones(ACT), (ACT,))


def _stochastic_actor(log_prob=False):
    net = nn.Sequential(low_rank_mlp(OBS, 2 * ACT, (16, 16)), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        return_log_prob=log_prob,
        spec=SPEC,
    )


def _deterministic_actor():
    return Actor(low_rank_mlp(OBS, ACT, (16, 16)), in_keys=["observation"], spec=SPEC)


def _discrete_actor():
    return ProbabilisticActor(
        TensorDictModule(low_rank_mlp(OBS, N_ACT, (16, 16)), ["observation"], ["logits"]),
        in_keys=["logits"],
        distribution_class=OneHotCategorical,
        spec=OneHot(N_ACT),
    )


def _q(out=1):
    class Q(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = low_rank_mlp(OBS + ACT, out, (16, 16))

        def forward(self, observation, action):
            return self.mlp(torch.cat([observation, action], -1))

    return ValueOperator(Q(), in_keys=["observation", "action"])


def _v():
    return ValueOperator(low_rank_mlp(OBS, 1, (16, 16)), in_keys=["observation"])


def _discrete_q(out_key="action_value"):
    return ValueOperator(low_rank_mlp(OBS, N_ACT, (16, 16)), in_keys=["observation"], out_keys=[out_key])


def _q_actor():
    return QValueActor(low_rank_mlp(OBS, N_ACT, (16, 16)), in_keys=["observation"], spec=OneHot(N_ACT))


def _distributional_q_actor():
    class Atoms(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = low_rank_mlp(OBS, ATOMS * N_ACT, (16, 16))

        def forward(self, x):
            return self.mlp(x).unflatten(-1, (ATOMS, N_ACT)).log_softmax(-2)

    return DistributionalQValueActor(
        Atoms(), in_keys=["observation"], spec=OneHot(N_ACT), support=torch.linspace(-1, 1, ATOMS)
    )


def _on_policy_fields(loss):
    def add(td, g):
        td.set(loss.tensor_keys.sample_log_prob, torch.randn(B, generator=g))
        td.set("advantage", torch.randn(B, 1, generator=g))
        td.set("value_target", torch.randn(B, 1, generator=g))
        td.set("loc", torch.randn(B, ACT, generator=g))  # the behaviour policy's parameters (KL penalty)
        td.set("scale", torch.rand(B, ACT, generator=g) + 0.5)

    return add


def _td(value_estimator=True, **kw):
    """Build a loss and, when it takes one, give it the TD(0) estimator (as TorchRL's examples do)."""

    def make(cls, *args):
        loss = cls(*args, **kw)
        if value_estimator:
            loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
        return loss

    return make


# name -> (build() -> (loss, the actor a collector runs or None), discrete actions, extra batch fields)
LOSS_CASES = {
    "SACLoss": (lambda: _td(action_spec=SPEC)(objectives.SACLoss, _stochastic_actor(), _q()), False, None),
    "DiscreteSACLoss": (
        lambda: _td(num_actions=N_ACT, action_space="one-hot")(
            objectives.DiscreteSACLoss, _discrete_actor(), _discrete_q()
        ),
        True,
        None,
    ),
    "REDQLoss": (
        lambda: _td(action_spec=SPEC, num_qvalue_nets=4)(objectives.REDQLoss, _stochastic_actor(True), _q()),
        False,
        None,
    ),
    "TQCLoss": (
        lambda: _td(action_spec=SPEC, num_qvalue_nets=3)(objectives.TQCLoss, _stochastic_actor(), _q(out=ATOMS)),
        False,
        None,
    ),
    "CrossQLoss": (lambda: _td(action_spec=SPEC)(objectives.CrossQLoss, _stochastic_actor(), _q()), False, None),
    "TD3Loss": (lambda: _td(action_spec=SPEC)(objectives.TD3Loss, _deterministic_actor(), _q()), False, None),
    "TD3BCLoss": (lambda: _td(action_spec=SPEC)(objectives.TD3BCLoss, _deterministic_actor(), _q()), False, None),
    "DDPGLoss": (lambda: _td()(objectives.DDPGLoss, _deterministic_actor(), _q()), False, None),
    "IQLLoss": (lambda: _td()(objectives.IQLLoss, _stochastic_actor(), _q(), _v()), False, None),
    "DiscreteIQLLoss": (
        lambda: _td(action_space="one-hot")(
            objectives.DiscreteIQLLoss, _discrete_actor(), _discrete_q("state_action_value"), _v()
        ),
        True,
        None,
    ),
    "CQLLoss": (lambda: _td(action_spec=SPEC)(objectives.CQLLoss, _stochastic_actor(), _q()), False, None),
    "DiscreteCQLLoss": (lambda: _td(action_space="one-hot")(objectives.DiscreteCQLLoss, _q_actor()), True, None),
    "DQNLoss": (lambda: _td(action_space="one-hot")(objectives.DQNLoss, _q_actor()), True, None),
    "DistributionalDQNLoss": (
        lambda: _td(False, gamma=0.99)(objectives.DistributionalDQNLoss, _distributional_q_actor()),
        True,
        None,
    ),
    "PPOLoss": (lambda: _td(False)(objectives.PPOLoss, _stochastic_actor(True), _v()), False, _on_policy_fields),
    "ClipPPOLoss": (
        lambda: _td(False)(objectives.ClipPPOLoss, _stochastic_actor(True), _v()),
        False,
        _on_policy_fields,
    ),
    "KLPENPPOLoss": (
        lambda: _td(False)(objectives.KLPENPPOLoss, _stochastic_actor(True), _v()),
        False,
        _on_policy_fields,
    ),
    "A2CLoss": (lambda: _td(False)(objectives.A2CLoss, _stochastic_actor(True), _v()), False, _on_policy_fields),
    "ReinforceLoss": (
        lambda: _td(False)(objectives.ReinforceLoss, _stochastic_actor(True), _v()),
        False,
        _on_policy_fields,
    ),
    "BCLoss": (lambda: _td(False, loss_function="l2")(objectives.BCLoss, _deterministic_actor()), False, None),
}


def _expected_networks(description: str) -> dict[str, tuple[str, bool]]:
    """``{network: (role, has targets)}`` from a SUPPORTED_LOSSES entry."""
    out = {}
    for part in description.split("; "):
        name, rest = part.split(" (", 1)
        out[name] = (rest.split(",")[0].split(":")[0].rstrip(")"), "targets" in rest and "no targets" not in rest)
    return out


def _loss_batch(i, discrete, extra):
    g = torch.Generator().manual_seed(100 + i)
    action = (
        torch.nn.functional.one_hot(torch.randint(N_ACT, (B,), generator=g), N_ACT)
        if discrete
        else torch.rand(B, ACT, generator=g) * 1.8 - 0.9
    )
    td = transition_batch(i, action=action)
    if extra is not None:
        extra(td, g)
    return td


def _total(out):
    return sum(v for k, v in out.items() if k.startswith("loss") and v.requires_grad)


def _has_targets(loss):
    return any(k.startswith("target_") and k.endswith("_params") for k in loss._modules)


def test_every_stock_torchrl_loss_is_tested_or_refused():
    stock = set()
    for module in (objectives, multiagent_objectives):
        for name, cls in vars(module).items():
            if inspect.isclass(cls) and issubclass(cls, objectives.LossModule) and cls is not objectives.LossModule:
                stock.add(name)
    assert stock == set(SUPPORTED_LOSSES) | set(UNSUPPORTED_LOSSES)
    assert not set(SUPPORTED_LOSSES) & set(UNSUPPORTED_LOSSES)
    assert list(LOSS_CASES) == list(SUPPORTED_LOSSES)  # the parametrised truncation test runs every supported loss


def test_doc_tables_are_the_registries():
    text = (Path(__file__).resolve().parents[1] / "docs" / "rank-adapter.md").read_text(encoding="utf-8")
    section = text.split("## Supported losses", 1)[1].split("\n## ", 1)[0]
    rows = [re.split(r"(?<!\\)\|", line)[1:-1] for line in section.splitlines() if line.startswith("| `")]
    table = [(cells[0].strip().strip("`"), cells[1].strip()) for cells in rows]
    assert table == [(k, v) for k, v in SUPPORTED_LOSSES.items()] + [(k, v) for k, v in UNSUPPORTED_LOSSES.items()]


@pytest.mark.parametrize("name", list(LOSS_CASES))
def test_truncation_through_every_supported_loss(name):
    build, discrete, extra = LOSS_CASES[name]
    torch.manual_seed(0)
    loss = build()
    assert type(loss).__name__ == name
    extra = extra(loss) if extra is not None else None
    updater = SoftUpdate(loss, eps=0.9) if _has_targets(loss) else None
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    adapter = RankAdapter(loss, opt, FixedRank(6), interval=2)  # then FixedRank(4): two events that change ranks
    # the networks found, their roles and their targets are the ones the registry (and so the docs) lists
    expected = _expected_networks(SUPPORTED_LOSSES[name])
    found = {}
    for site in adapter.sites:
        found.setdefault(site.network_name, (site.role, site.target_w1 is not None))
        assert found[site.network_name] == (site.role, site.target_w1 is not None), site.path
    assert found == expected
    # optimise, keeping the last graph alive across the events
    for i in range(4):
        out = loss(_loss_batch(i, discrete, extra))
        total = _total(out)
        assert torch.isfinite(total), name
        opt.zero_grad()
        total.backward()
        opt.step()
        if updater is not None:
            updater.step()
        event = adapter.step()
        if event is not None:
            assert event.changed
            changed = {r.layer for r in event.layers if r.changed}
            for s in adapter.sites:  # dropped at the event for exactly the resized factors
                assert (s.w1 in opt.state, s.w2 in opt.state) == (
                    (False, False) if s.path in changed else (True, True)
                ), s.path
            adapter.rule = FixedRank(4)
    assert set(adapter.ranks.values()) == {4} and len(adapter.history) == 2
    for s in adapter.sites:  # shapes: online, target and the module template agree
        assert s.w1.shape[-1] == s.w2.shape[-2] == 4 and s.template.rank == 4, s.path
        if s.target_w1 is not None:
            assert s.target_w1.shape == s.w1.shape and s.target_w2.shape == s.w2.shape, s.path
    # the next step trains the new tensors, with Adam state of the new shapes
    before = {s.path: (s.w1.detach().clone(), s.w2.detach().clone()) for s in adapter.sites}
    out = loss(_loss_batch(9, discrete, extra))
    opt.zero_grad()
    _total(out).backward()
    opt.step()
    for s in adapter.sites:
        w1, w2 = before[s.path]
        assert not (torch.equal(s.w1, w1) and torch.equal(s.w2, w2)), s.path
        assert opt.state[s.w1]["exp_avg"].shape == s.w1.shape, s.path
    # target updates lerp the resized tensors
    if updater is not None:
        pairs = [(s.w1, s.target_w1) for s in adapter.sites if s.target_w1 is not None]
        pairs += [(s.w2, s.target_w2) for s in adapter.sites if s.target_w2 is not None]
        assert pairs
        snap = [(on.detach().clone(), tg.detach().clone()) for on, tg in pairs]
        updater.step()
        for (_, tg), (on0, tg0) in zip(pairs, snap):
            torch.testing.assert_close(tg, tg0 * 0.9 + on0 * 0.1)
    # each scope touches only its own networks
    for scope in ("actor", "critic"):
        if not any(r == scope for r, _ in expected.values()):
            with pytest.raises(AdaRLValueError, match="no LowRankLinear"):
                RankAdapter(loss, opt, FixedRank(2), interval=1, scope=scope)
            continue
        ranks = adapter.ranks
        RankAdapter(loss, opt, FixedRank(3 if scope == "actor" else 2), interval=1, scope=scope).adapt()
        for s in adapter.sites:
            want = (3 if scope == "actor" else 2) if s.role == scope else ranks[s.path]
            assert s.rank == want and s.template.rank == want, (scope, s.path)
    out = loss(_loss_batch(10, discrete, extra))
    _total(out).backward()


def test_refused_losses_are_refused_by_name():
    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = low_rank_mlp(OBS, 1, (16, 16))

        def forward(self, observation):
            return self.mlp(observation)

    disc = ValueOperator(Net(), in_keys=["observation"], out_keys=["d_logits"])
    loss = objectives.GAILLoss(disc)
    opt = torch.optim.Adam(loss.parameters())
    with pytest.raises(
        AdaRLValueError,
        match=r"does not support TorchRL's GAILLoss: trains a discriminator.*"
        r"Supported TorchRL losses: \['A2CLoss'",
    ):
        RankAdapter(loss, opt, FixedRank(2), interval=1)

    class MyGAIL(objectives.GAILLoss):  # a subclass of a refused loss is refused
        pass

    with pytest.raises(AdaRLValueError, match="GAILLoss"):
        check_loss_supported(MyGAIL(disc))

    class MySAC(objectives.SACLoss):  # a subclass of a supported one is not
        pass

    check_loss_supported(MySAC(_stochastic_actor(), _q(), action_spec=SPEC))


def test_ddpg_loss_actor_and_value_network_with_targets():
    # DDPGLoss also holds a wrapper, actor_critic = [actor_network, value_network], with no parameters of its own:
    # the layers used to be found through it, all labelled "critic", without the value network's targets
    from torchrl.objectives import DDPGLoss

    torch.manual_seed(0)
    actor = Actor(low_rank_mlp(OBS, ACT, (16, 16)), in_keys=["observation"])
    loss = DDPGLoss(actor, ValueOperator(QNet(), in_keys=["observation", "action"]), loss_function="l2")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    updater = SoftUpdate(loss, eps=0.9)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=2, scope="critic")
    assert adapter.layers == {"value_network.module.mlp.0": "critic", "value_network.module.mlp.2": "critic"}
    run(loss, opt, adapter, 4, transition_batch, updater)
    check_targets(loss, ["value_network"])
    assert actor.module[2].rank == 16  # scope="critic" leaves the actor alone
    actor_adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor")
    assert set(actor_adapter.layers.values()) == {"actor"}
    actor_adapter.adapt()
    assert actor.module[2].rank == 2 and loss.value_network.module.mlp[2].rank == 3
    run(loss, opt, actor_adapter, 1, transition_batch, updater)


def test_registered_on_a_trainer_the_ranks_share_its_x_axis():
    from torchrl.collectors import Collector
    from torchrl.envs import GymEnv
    from torchrl.objectives import SACLoss
    from torchrl.record.loggers import Logger
    from torchrl.trainers import Trainer

    class Recording(Logger):
        def __init__(self):
            super().__init__(exp_name="rank-axis", log_dir=".")
            self.logged = []

        def _create_experiment(self):
            return None

        def log_scalar(self, name, value, step=None):
            self.logged.append((name, step))

        def log_video(self, *args, **kwargs):
            pass

        def log_hparams(self, *args, **kwargs):
            pass

        def log_histogram(self, *args, **kwargs):
            pass

        def __repr__(self):
            return "Recording()"

    env = GymEnv("Pendulum-v1")
    torch.manual_seed(0)
    net = nn.Sequential(low_rank_mlp(3, 2, (16, 16)), NormalParamExtractor())
    actor = ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        spec=env.action_spec,
    )

    class Q(nn.Module):
        def __init__(self):
            super().__init__()
            self.mlp = low_rank_mlp(4, 1, (16, 16))

        def forward(self, observation, action):
            return self.mlp(torch.cat([observation, action], -1))

    for own_logger in (True, False):  # the adapter's own logger, or (none given) the trainer's
        loss = SACLoss(actor, ValueOperator(Q(), in_keys=["observation", "action"]), action_spec=env.action_spec)
        opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
        logger = Recording()
        trainer = Trainer(
            collector=Collector(env, actor, frames_per_batch=16, total_frames=64),
            total_frames=64,
            frame_skip=1,
            optim_steps_per_batch=3,
            loss_module=loss,
            optimizer=opt,
            logger=logger,
            progress_bar=False,
            log_interval=0,
        )
        adapter = RankAdapter(loss, opt, FixedRank(3), interval=4, scope="actor", logger=logger if own_logger else None)
        adapter.register(trainer)
        trainer.train()
        ranks = [step for name, step in logger.logged if name.startswith("rank/")]
        losses = {step for name, step in logger.logged if name == "loss_actor"}
        assert [e.step for e in adapter.history] == [4, 8, 12]  # events at optimisation steps...
        assert ranks == [32, 32, 48, 48, 64, 64]  # ...logged at the collected frames, as the losses are
        assert set(ranks) <= losses


def _shared_actor_td3_losses():
    """Two TD3 losses on one actor (TorchRL's own tests build losses this way), each with its own critic, target
    networks, optimiser, SoftUpdate and RankAdapter."""
    torch.manual_seed(0)
    actor = Actor(low_rank_mlp(OBS, ACT, (16, 16)), in_keys=["observation"])
    out = []
    for _ in range(2):
        loss = TD3Loss(actor, ValueOperator(QNet(), in_keys=["observation", "action"]), bounds=(-1.0, 1.0))
        loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
        out.append((loss, torch.optim.Adam(loss.parameters(), lr=1e-3), SoftUpdate(loss, eps=0.9)))
    return actor, out


def _train(pairs, steps=2):
    for i in range(steps):
        for loss, opt, updater in pairs:
            out = loss(transition_batch(i))
            opt.zero_grad()
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            opt.step()
            updater.step()


def test_two_losses_sharing_an_actor_both_follow_either_adapter():
    """Issue 29.2: after one adapter truncates the shared actor, the other loss's target actor, cached views and
    optimiser state follow (before: it kept the old shape and weights, and the other adapter skipped the layer)."""
    actor, pairs = _shared_actor_td3_losses()
    adapters = [
        RankAdapter(loss, opt, FixedRank(r), interval=1, scope="actor") for (loss, opt, _), r in zip(pairs, (4, 2))
    ]
    critic_only = RankAdapter(pairs[1][0], pairs[1][1], FixedRank(8), interval=1, scope="critic")  # noqa: F841
    _train(pairs)
    for adapter, rank in zip(adapters, (4, 2)):
        assert adapter.adapt().changed
        for loss, opt, _ in pairs:
            online, target = loss.actor_network_params, loss._modules["target_actor_network_params"]
            for key in online.keys(True, True):
                assert online.get(key).shape == target.get(key).shape, key
                if key[-1] in ("w1", "w2"):
                    assert torch.equal(online.get(key), target.get(key)), key  # synced to the new factors
                    assert online.get(key).shape[-1 if key[-1] == "w1" else -2] == rank
                    assert online.get(key) not in opt.state  # no Adam moments of the old basis
        _train(pairs)  # both losses, optimisers and SoftUpdates run on the new shapes
    assert actor.module[0].rank == 2 and adapters[0].ranks == adapters[1].ranks


def test_resize_to_ranks_resizes_the_targets_of_a_second_loss_on_a_resized_actor():
    _, pairs = _shared_actor_td3_losses()
    ranks = {"actor_network.module.0": 3, "actor_network.module.2": 3}
    assert resize_to_ranks(pairs[0][0], ranks, pairs[0][1])
    resize_to_ranks(pairs[1][0], ranks, pairs[1][1])  # the shared actor already has them: its targets not yet
    target = pairs[1][0]._modules["target_actor_network_params"]
    assert target.get(("module", "0", "w1")).shape[-1] == 3 and target.get(("module", "2", "w2")).shape[-2] == 3
