"""RankAdapter on SACLoss: safe in-place truncation, targets, optimisers, caches, checkpoints, rules, history."""

import io
import math
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators

from adarl.core.adapter import RankAdapter, find_low_rank_layers, resize_to_ranks
from adarl.core.lowrank import LowRankLinear, factor_svd, low_rank_mlp
from adarl.core.lr_schedule import make_lr_scheduler
from adarl.core.rank import EnergyRule, FixedRank, InclusiveEnergyRule, PolicyFitRule
from adarl.errors import AdaRLValueError, CheckpointError

warnings.filterwarnings("ignore", category=UserWarning)
OBS, ACT, B = 5, 2, 16
ACTOR_L0 = "actor_network.module.0.module.0.0"
ACTOR_L1 = "actor_network.module.0.module.0.2"
Q_L0 = "qvalue_network.module.mlp.0"
Q_L1 = "qvalue_network.module.mlp.2"


class QNet(nn.Module):
    def __init__(self, obs=OBS, act=ACT):
        super().__init__()
        self.mlp = low_rank_mlp(obs + act, 1, (16, 16))

    def forward(self, observation, action):
        return self.mlp(torch.cat([observation, action], -1))


def make_actor(obs=OBS, act=ACT, spec=None):
    net = nn.Sequential(low_rank_mlp(obs, 2 * act, (16, 16)), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        return_log_prob=True,
        spec=spec,
    )


def make_sac(seed=0, obs=OBS, act=ACT, spec=None):
    torch.manual_seed(seed)
    actor = make_actor(obs, act, spec)
    qv = ValueOperator(QNet(obs, act), in_keys=["observation", "action"])
    loss = SACLoss(actor, qv, target_entropy=-float(act), loss_function="l2")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    return loss


def fake_batch(seed=None, n=B, obs=OBS, act=ACT):
    g = torch.Generator().manual_seed(seed) if seed is not None else None
    return TensorDict(
        {
            "observation": torch.randn(n, obs, generator=g),
            "action": torch.rand(n, act, generator=g) * 1.8 - 0.9,
            "next": {
                "observation": torch.randn(n, obs, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )


def total_loss(td):
    return sum(v for k, v in td.items() if k.startswith("loss_"))


def train(loss, opt, updater=None, steps=3, adapter=None, seed=None):
    """A hand-written SAC loop; keeps last step's graph alive (as real loops do) across adapter events."""
    events, value = [], None
    for i in range(steps):
        value = total_loss(loss(fake_batch(None if seed is None else seed + i)))
        assert torch.isfinite(value), value
        opt.zero_grad()
        value.backward()
        opt.step()
        if updater is not None:
            updater.step()
        if adapter is not None:
            ev = adapter.step()
            if ev is not None:
                events.append(ev)
    return value, events


def online_target_pairs(loss):
    """(key, online, target) for every Q factor."""
    return [
        (k, loss.qvalue_network_params.get(k), loss.target_qvalue_network_params.get(k))
        for k in loss.qvalue_network_params.keys(True, True)
    ]


def dense(w1, w2):
    return w1.detach().double() @ w2.detach().double()


def proj(w, k):
    u, s, vh = torch.linalg.svd(w, full_matrices=False)
    return (u[..., :k] * s[..., None, :k]) @ vh[..., :k, :]


# --------------------------------------------------------------------------------------------------------------


def test_finds_layers_behind_functional_params():
    loss = make_sac()
    sites, searched = find_low_rank_layers(loss)
    paths = {s.path: s for s in sites}
    assert set(paths) == {ACTOR_L0, ACTOR_L1, Q_L0, Q_L1}
    assert paths[ACTOR_L0].role == "actor" and paths[Q_L0].role == "critic"
    # actor: the actor's own parameters; critic: the stacked [2, ...] Parameters the loss trains under vmap
    assert paths[ACTOR_L0].w1 is loss.actor_network.module[0].module[0][0].w1
    assert paths[Q_L0].w1 is loss.qvalue_network_params.get(("module", "mlp", "0", "w1"))
    assert paths[Q_L0].batch_shape == (2,)
    assert paths[Q_L0].target_w1 is loss.target_qvalue_network_params.get(("module", "mlp", "0", "w1"))
    assert paths[ACTOR_L0].target_w1 is None  # SACLoss has no target actor by default
    assert any(s.startswith("actor_network") for s in searched) and any(
        s.startswith("qvalue_network") for s in searched
    )


@pytest.mark.parametrize("optim_kw", [{"fused": True}, {"foreach": True}, {"foreach": False}])
def test_sac_training_continues_after_repeated_truncations(optim_kw):
    loss = make_sac()
    updater = SoftUpdate(loss, eps=0.9)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3, **optim_kw)
    params_before = {id(p): p for p in loss.parameters()}
    adapter = RankAdapter(loss, opt, EnergyRule(0.98), interval=3)
    ranks0 = adapter.ranks
    value, events = train(loss, opt, updater, steps=10, adapter=adapter)
    assert len(events) == 3 and all(ev.changed for ev in events)
    assert torch.isfinite(value)
    # EnergyRule (literal Eq. 10) removes at least one direction per event
    for path, r in adapter.ranks.items():
        assert r <= ranks0[path] - 3
    # parameter objects keep their identity; the optimiser and SoftUpdate still own them
    assert {id(p): p for p in loss.parameters()}.keys() == params_before.keys()
    assert {id(p) for g in opt.param_groups for p in g["params"]} == set(params_before)

    # one more step: every truncated factor moves, and its Adam state has the new shape
    factors = [s.w1 for s in adapter.sites] + [s.w2 for s in adapter.sites]
    before = [f.detach().clone() for f in factors]
    train(loss, opt, updater, steps=1)
    for f, b in zip(factors, before):
        assert f.shape == b.shape and not torch.equal(f, b)
        assert opt.state[f]["exp_avg"].shape == f.shape and opt.state[f]["exp_avg_sq"].shape == f.shape

    # targets have the online shapes, and SoftUpdate lerps the new tensors
    pairs = online_target_pairs(loss)
    for _, on, tg in pairs:
        assert on.shape == tg.shape
    snap = [(on.detach().clone(), tg.detach().clone()) for _, on, tg in pairs]
    updater.step()
    for (_, _, tg), (on0, tg0) in zip(pairs, snap):
        torch.testing.assert_close(tg, tg0 * 0.9 + on0 * 0.1)


def test_truncation_is_the_best_rank_k_projection_and_sync_targets():
    loss = make_sac()
    updater = SoftUpdate(loss, eps=0.5)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-2)
    train(loss, opt, updater, steps=3)
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, target_mode="sync")
    before = {s.path: dense(s.w1, s.w2) for s in adapter.sites}
    adapter.adapt()
    for s in adapter.sites:
        assert s.rank == 3
        torch.testing.assert_close(dense(s.w1, s.w2), proj(before[s.path], 3))
        if s.target_w1 is not None:
            assert torch.equal(s.target_w1, s.w1) and torch.equal(s.target_w2, s.w2)
            assert s.target_w1 is not s.w1  # a copy, not an alias
    # balanced factors: W1 = U sqrt(S), W2 = sqrt(S) V^T
    s = adapter.sites[0]
    torch.testing.assert_close(s.w1.norm(dim=-2), s.w2.norm(dim=-1))


def test_project_target_mode_keeps_the_polyak_lag():
    loss = make_sac()
    updater = SoftUpdate(loss, eps=0.5)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-2)
    train(loss, opt, updater, steps=4)
    site = next(s for s in find_low_rank_layers(loss)[0] if s.path == Q_L1)
    w1, w2 = site.w1.detach().double().clone(), site.w2.detach().double().clone()
    t1, t2 = site.target_w1.double().clone(), site.target_w2.double().clone()
    assert not torch.allclose(t1, w1)  # the target lags
    k = 5
    adapter = RankAdapter(loss, opt, FixedRank(k), interval=1, target_mode="project", scope="critic")
    event = adapter.adapt()
    rec = next(r for r in event.layers if r.layer == Q_L1)
    assert rec.target == "project"
    assert site.target_w1.shape == site.w1.shape == (2, 16, k)
    # basis-free form of the projection: W1t' W2t' = W1t pinv(W1) Pi_k(W1 W2) pinv(W2) W2t
    expected = t1 @ torch.linalg.pinv(w1) @ proj(w1 @ w2, k) @ torch.linalg.pinv(w2) @ t2
    torch.testing.assert_close(dense(site.target_w1, site.target_w2), expected, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(dense(site.w1, site.w2), proj(w1 @ w2, k), rtol=1e-4, atol=1e-5)
    # a target equal to the online network stays equal to it (= the online projection)
    loss2 = make_sac(seed=1)
    opt2 = torch.optim.Adam(loss2.parameters())
    ad2 = RankAdapter(loss2, opt2, FixedRank(4), interval=1, target_mode="project", scope="critic")
    before = {s.path: dense(s.w1, s.w2) for s in ad2.sites}
    ad2.adapt()
    for s in ad2.sites:
        torch.testing.assert_close(dense(s.target_w1, s.target_w2), proj(before[s.path], 4), rtol=1e-4, atol=1e-5)
    SoftUpdate(loss2, eps=0.5).step()


@pytest.mark.parametrize("k", [3, 12])
def test_project_keeps_target_factors_in_the_online_basis(k):
    # SoftUpdate lerps factors elementwise, so the target factors must stay in the online factors' basis (same
    # signs / rotation of the bottleneck), not only give the right product.
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    sites = {s.path: s for s in find_low_rank_layers(loss)[0]}
    with torch.no_grad():
        for s in sites.values():
            if s.target_w1 is not None:
                s.target_w1.copy_(s.w1 + 1e-3 * torch.randn_like(s.w1))
                s.target_w2.copy_(s.w2 + 1e-3 * torch.randn_like(s.w2))
    RankAdapter(loss, opt, FixedRank(k), interval=1, target_mode="project", scope="critic").adapt()
    for s in sites.values():
        if s.target_w1 is not None:
            assert (s.target_w1 - s.w1).abs().max() < 0.02, s.path
            assert (s.target_w2 - s.w2).abs().max() < 0.02, s.path


def test_project_falls_back_to_sync_when_ill_conditioned():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    site = next(s for s in find_low_rank_layers(loss)[0] if s.path == Q_L1)
    with torch.no_grad():
        site.w1[..., -1] = 0.0  # a singular R1
        site.target_w1.copy_(site.w1 + 0.01)
    adapter = RankAdapter(loss, opt, FixedRank(6), interval=1, target_mode="project", scope="critic")
    event = adapter.adapt()
    rec = next(r for r in event.layers if r.layer == Q_L1)
    assert rec.target.startswith("sync (fallback")
    assert torch.equal(site.target_w1, site.w1) and torch.equal(site.target_w2, site.w2)


def test_loss_caches_are_refreshed():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=1)
    assert "_cached_detached_qvalue_params" in loss._cache
    adapter = RankAdapter(loss, opt, FixedRank(4), interval=1, scope="critic")
    adapter.adapt()
    train(loss, opt, steps=1)
    cached = loss._cache["_cached_detached_qvalue_params"].get(("module", "mlp", "0", "w1"))
    assert cached.shape == (2, 16, 4)
    assert torch.equal(cached, loss.qvalue_network_params.get(("module", "mlp", "0", "w1")))


@pytest.mark.parametrize(
    "scope, changed",
    [("actor", {ACTOR_L0, ACTOR_L1}), ("critic", {Q_L0, Q_L1}), ("both", {ACTOR_L0, ACTOR_L1, Q_L0, Q_L1})],
)
def test_scope_touches_only_its_layers(scope, changed):
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=1)
    snapshot = {k: v.detach().clone() for k, v in loss.state_dict().items()}
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, scope=scope)
    assert set(adapter.ranks) == changed
    adapter.adapt()
    prefixes = tuple(
        p.replace("actor_network.", "actor_network_params.").replace("qvalue_network.", "qvalue_network_params.")
        for p in changed
    )
    prefixes += tuple("target_" + p for p in prefixes if p.startswith("qvalue"))
    after = loss.state_dict()
    for k, v in snapshot.items():
        touched = k.startswith(prefixes) and k.rsplit(".", 1)[-1] in ("w1", "w2")
        if touched:
            assert after[k].shape[-1 if k.endswith("w1") else -2] == 3, k
        else:
            assert torch.equal(after[k], v), k
    # optimiser state is dropped for exactly the truncated parameters
    truncated = {id(s.w1) for s in adapter.sites} | {id(s.w2) for s in adapter.sites}
    for p in loss.parameters():
        assert (p in opt.state) == (id(p) not in truncated)


def test_history_records_and_truncation_error():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=2)
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=2)
    adapter.step()
    assert adapter.history == []
    spectra = {s.path: factor_svd(s.w1, s.w2)[1] for s in adapter.sites}
    event = adapter.step()
    assert adapter.history == [event] and event.step == 2 and event.index == 0
    recs = {r.layer: r for r in event.layers}
    assert set(recs) == set(spectra)
    a = recs[ACTOR_L1]
    assert a.network == "actor" and a.old_rank == 16 and a.new_rank == 3 and a.skipped is None
    s = spectra[ACTOR_L1]
    assert a.singular_values == pytest.approx(s.tolist())
    assert a.truncation_error == pytest.approx(math.sqrt(sum(x * x for x in s.tolist()[3:])))
    assert a.retained_energy == pytest.approx(float(s[:3].sum() / s.sum()))
    q = recs[Q_L0]
    assert q.network == "critic" and len(q.singular_values) == 2 and len(q.singular_values[0]) == 7
    s = spectra[Q_L0]
    assert q.truncation_error == pytest.approx(s[:, 3:].pow(2).sum(-1).sqrt().tolist())
    assert q.member_ranks == [3, 3] and q.target == "sync"
    assert event.ranks == adapter.ranks and event.as_dict()["layers"][0]["layer"] == recs[ACTOR_L0].layer


def test_ensemble_takes_the_largest_member_rank():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    site = next(s for s in find_low_rank_layers(loss)[0] if s.path == Q_L1)
    with torch.no_grad():  # member 0 has exact rank 2, member 1 is a generic full-rank matrix
        site.w1[0, :, 2:] = 0.0
    adapter = RankAdapter(loss, opt, InclusiveEnergyRule(0.9), interval=1, scope="critic")
    rec = next(r for r in adapter.adapt().layers if r.layer == Q_L1)
    assert rec.member_ranks[0] <= 2 < rec.member_ranks[1]
    assert rec.new_rank == max(rec.member_ranks) == site.rank


def test_skip_changes_nothing():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=1)
    sch = make_lr_scheduler(opt, warmup_steps=2)
    sch.step(), sch.step()
    calls = []
    adapter = RankAdapter(loss, opt, FixedRank(16), interval=1, lr_schedulers=[sch], on_truncate=[calls.append])
    state = {k: v.clone() for k, v in loss.state_dict().items()}
    n_opt_state = len(opt.state)
    event = adapter.adapt()
    assert not event.changed and calls == []
    assert all(r.skipped for r in event.layers)
    assert all(torch.equal(loss.state_dict()[k], v) for k, v in state.items())
    assert len(opt.state) == n_opt_state and opt.param_groups[0]["lr"] > 0


def test_zero_spectrum_is_skipped_with_reason():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    site = next(s for s in find_low_rank_layers(loss)[0] if s.path == ACTOR_L0)
    with torch.no_grad():
        site.w1.zero_()
    adapter = RankAdapter(loss, opt, EnergyRule(0.9), interval=1, scope="actor")
    rec = next(r for r in adapter.adapt().layers if r.layer == ACTOR_L0)
    assert rec.new_rank == rec.old_rank and "zero" in rec.skipped


def test_lr_restart_callbacks_and_logger():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters(), lr=0.1)
    sch = make_lr_scheduler(opt, warmup_steps=2, total_steps=100)
    logged, calls = [], []

    class Logger:
        def log_scalar(self, name, value, step=None):
            logged.append((name, value, step))

    adapter = RankAdapter(
        loss, opt, EnergyRule(0.98), interval=3, lr_schedulers=[sch], on_truncate=calls.append, logger=Logger()
    )
    for _ in range(3):
        train(loss, opt, steps=1)
        sch.step()
        assert opt.param_groups[0]["lr"] > 0 or adapter.step_count == 0
        adapter.step()
    assert opt.param_groups[0]["lr"] == 0.0  # restarted: warm-up from zero
    assert len(calls) == 1 and calls[0] is adapter.history[-1]
    assert {name for name, _, _ in logged} == {f"rank/{n}" for n in adapter.names.values()}
    assert all(step == 3 and isinstance(v, float) for _, v, step in logged)
    sch.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.05 * 0.5 * (1 + math.cos(math.pi * 4 / 100)))


def test_policy_fit_rule_measures_outputs():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=2)
    rb = ReplayBuffer(storage=LazyTensorStorage(64), batch_size=32)
    rb.extend(fake_batch(seed=3, n=64))
    seen = {}

    class Recording(PolicyFitRule):
        def select(self, s, current_rank, min_rank, fit):
            seen[len(seen)] = {r: fit(r) for r in (1, current_rank)}
            return super().select(s, current_rank, min_rank, fit)

    adapter = RankAdapter(loss, opt, Recording(lam=0.05), interval=1, fit_data=rb)
    event = adapter.adapt()
    # actor: 2 layers x 1 member; critic: 2 layers x 2 members
    assert len(seen) == 6
    for d in seen.values():
        values = list(d.values())
        assert values[-1] == pytest.approx(0.0, abs=1e-5)  # current rank reproduces the outputs
        assert values[0] > 1e-4  # rank 1 does not
    assert any(r.changed for r in event.layers)
    # the outputs stay close: lam bounds the accepted distance per removed rank
    train(loss, opt, steps=2)


def test_policy_fit_needs_data_and_callable_fit_data_works():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    with pytest.raises(AdaRLValueError, match="fit_data"):
        RankAdapter(loss, opt, PolicyFitRule(), interval=1)
    adapter = RankAdapter(loss, opt, PolicyFitRule(lam=10.0), interval=1, fit_data=lambda: fake_batch(seed=1))
    event = adapter.adapt()
    assert all(r.new_rank == 1 for r in event.layers)  # a huge lam: rank costs more than any distance
    train(loss, opt, steps=1)


def test_collector_policy_shares_the_truncated_tensors():
    from torchrl.collectors import Collector
    from torchrl.envs import GymEnv

    env = GymEnv("Pendulum-v1")
    loss = make_sac(obs=3, act=1, spec=env.action_spec)
    opt = torch.optim.Adam(loss.parameters())
    collector = Collector(env, loss.actor_network, frames_per_batch=8, total_frames=-1)
    adapter = RankAdapter(loss, opt, FixedRank(2), interval=1, scope="actor")
    adapter.adapt()
    policy = collector.policy
    for site in adapter.sites:
        key = site.key
        mod = policy.module[0].module[0][int(key[-1])]
        assert mod.w1 is site.w1 and mod.w1 is loss.actor_network_params.get(key + ("w1",))
        assert mod.w1.shape[-1] == 2
    td = fake_batch(seed=0, obs=3, act=1).select("observation")
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        a = policy(td.clone())["action"]
        with loss.actor_network_params.to_module(loss.actor_network):
            b = loss.actor_network(td.clone())["action"]
    torch.testing.assert_close(a, b)
    out = collector.rollout()
    assert out.numel() == 8 and torch.isfinite(out["action"]).all()
    collector.update_policy_weights_()
    collector.shutdown()


def test_checkpoint_round_trip_across_rank_change():
    loss = make_sac(seed=0)
    updater = SoftUpdate(loss, eps=0.9)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    sch = make_lr_scheduler(opt, warmup_steps=2)
    adapter = RankAdapter(loss, opt, EnergyRule(0.95), interval=2, lr_schedulers=[sch])
    for _ in range(5):
        train(loss, opt, updater, steps=1, adapter=adapter)
        sch.step()
    assert len(adapter.history) == 2
    buf = io.BytesIO()  # through torch.save/load, as a real checkpoint (and no aliasing of live tensors)
    torch.save({"loss": loss.state_dict(), "opt": opt.state_dict(), "adapter": adapter.state_dict()}, buf)
    buf.seek(0)
    ckpt = torch.load(buf)  # weights_only: the adapter state is plain data

    fresh = make_sac(seed=123)
    fresh_updater = SoftUpdate(fresh, eps=0.9)  # before loading: SoftUpdate() copies online into target
    fresh_opt = torch.optim.Adam(fresh.parameters(), lr=1e-3)
    fresh_sch = make_lr_scheduler(fresh_opt, warmup_steps=2)
    fresh_adapter = RankAdapter(fresh, fresh_opt, EnergyRule(0.95), interval=2, lr_schedulers=[fresh_sch])
    with pytest.raises((RuntimeError, ValueError), match="size|Failed to update"):  # torch's or tensordict's
        fresh.load_state_dict(ckpt["loss"])  # shapes differ: the reason for resize_to_ranks
    with pytest.raises(CheckpointError, match="resize_to_ranks"):
        fresh_adapter.load_state_dict(ckpt["adapter"])
    changed = resize_to_ranks(fresh, ckpt["adapter"], fresh_opt)
    assert {p: new for p, (_, new) in changed.items()} == adapter.ranks
    fresh.load_state_dict(ckpt["loss"])
    fresh_opt.load_state_dict(ckpt["opt"])
    fresh_adapter.load_state_dict(ckpt["adapter"])
    assert fresh_adapter.ranks == adapter.ranks and fresh_adapter.step_count == adapter.step_count
    assert [e.as_dict() for e in fresh_adapter.history] == [e.as_dict() for e in adapter.history]
    assert vars(fresh_sch.lr_lambdas[0]) == vars(sch.lr_lambdas[0])
    for k, v in loss.state_dict().items():
        assert torch.equal(fresh.state_dict()[k], v), k
    # identical outputs, and an identical next optimisation step
    for lm, o, u in ((loss, opt, updater), (fresh, fresh_opt, fresh_updater)):
        torch.manual_seed(7)
        train(lm, o, u, steps=2, seed=11)
    for k, v in loss.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[k], v, rtol=0, atol=0, msg=k)

    # the loss's own state_dict also gives the ranks
    other = make_sac(seed=5)
    resize_to_ranks(other, ckpt["loss"])
    other.load_state_dict(ckpt["loss"])


def test_resize_to_ranks_errors():
    loss = make_sac()
    with pytest.raises(CheckpointError, match="unknown layers"):
        resize_to_ranks(loss, {"actor_network.nope": 2})
    with pytest.raises(CheckpointError, match="integer in"):
        resize_to_ranks(loss, {ACTOR_L0: 99})
    with pytest.raises(CheckpointError, match="integers"):
        resize_to_ranks(loss, {"ranks": {ACTOR_L0: "2"}})
    assert resize_to_ranks(loss, {ACTOR_L0: 2}) == {ACTOR_L0: (5, 2)}
    assert loss.actor_network.module[0].module[0][0].w1.shape == (16, 2)
    assert resize_to_ranks(loss, {ACTOR_L0: 4}) == {ACTOR_L0: (2, 4)}  # growing zero-pads
    assert loss.actor_network.module[0].module[0][0].w2.shape == (4, 5)


def test_validation_errors():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    rule = EnergyRule(0.9)
    for kwargs, match in [
        ({"interval": 0}, "interval"),
        ({"interval": 1, "scope": "policy"}, "scope"),
        ({"interval": 1, "target_mode": "copy"}, "target_mode"),
        ({"interval": 1, "min_rank": 0}, "min_rank"),
        ({"interval": 1, "lr_schedulers": [object()]}, "lr_schedulers"),
        ({"interval": 1, "on_truncate": [1]}, "on_truncate"),
    ]:
        with pytest.raises(AdaRLValueError, match=match):
            RankAdapter(loss, opt, rule, **kwargs)
    torch.manual_seed(0)
    dense_actor = ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(nn.Linear(OBS, 2 * ACT), NormalParamExtractor()), ["observation"], ["loc", "scale"]
        ),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
    )
    dense_loss = SACLoss(dense_actor, ValueOperator(QNet(), in_keys=["observation", "action"]), target_entropy=-2.0)
    with pytest.raises(AdaRLValueError, match="actor_network") as err:
        RankAdapter(dense_loss, opt, rule, interval=1, scope="actor")
    assert "qvalue_network" in str(err.value)


def test_min_rank_is_respected():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    adapter = RankAdapter(loss, opt, EnergyRule(0.5), interval=1, min_rank=4)
    for _ in range(3):
        adapter.adapt()
    assert adapter.ranks[ACTOR_L0] == 4 and adapter.ranks[Q_L1] == 4
    train(loss, opt, steps=1)


def test_template_modules_stay_consistent():
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    RankAdapter(loss, opt, FixedRank(3), interval=1).adapt()
    ranks = {name: m.rank for name, m in loss.qvalue_network.named_modules() if isinstance(m, LowRankLinear)}
    assert ranks == {"module.mlp.0": 3, "module.mlp.2": 3}


def test_num_threads_applies_during_the_event_only(monkeypatch):
    import adarl.core.adapter as adapter_mod

    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    seen = []
    real = adapter_mod.factor_svd

    def spy(w1, w2):
        seen.append(torch.get_num_threads())
        return real(w1, w2)

    monkeypatch.setattr(adapter_mod, "factor_svd", spy)
    before = torch.get_num_threads()
    want = 2 if before == 1 else 1
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, num_threads=want)
    adapter.adapt()
    assert seen and set(seen) == {want}
    assert torch.get_num_threads() == before
    with pytest.raises(AdaRLValueError, match="num_threads"):
        RankAdapter(loss, opt, FixedRank(3), interval=1, num_threads=0)


# --------------------------------------------------------------------------------------------------------------
# issue 22: NaN/inf at an event, optimisers that miss parameters, integer arguments
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("with_acceptance", [False, True])
def test_non_finite_factors_are_skipped_with_a_reason_and_the_rest_changes(bad, with_acceptance):
    from adarl.core.acceptance import ProjectionAcceptance

    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=1)
    sites = {s.path: s for s in find_low_rank_layers(loss)[0]}
    with torch.no_grad():
        sites[ACTOR_L1].w1[0, 0] = bad  # one actor layer diverged
        sites[Q_L0].w2[1, 0, 0] = bad  # one member of the critic ensemble diverged
    before = {p: (s.w1.detach().clone(), s.w2.detach().clone()) for p, s in sites.items()}
    kwargs = (
        {"acceptance": ProjectionAcceptance(1e9, 1e9), "fit_data": lambda: fake_batch(seed=4)}
        if with_acceptance
        else {}
    )
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=1, **kwargs)
    event = adapter.adapt()  # no LinAlgError from the SVD
    recs = {r.layer: r for r in event.layers}
    for path in (ACTOR_L1, Q_L0):
        assert recs[path].new_rank == recs[path].old_rank and "non-finite values" in recs[path].skipped
        torch.testing.assert_close(sites[path].w1, before[path][0], equal_nan=True)  # untouched
    # the healthy layers share a network with a broken one: with the acceptance step (which measures the network's
    # outputs, non-finite here) they keep their rank and say why; without it they change
    for path, old in ((ACTOR_L0, 5), (Q_L1, 16)):
        if with_acceptance:
            assert recs[path].new_rank == old and "outputs on fit_data are non-finite" in recs[path].skipped
        else:
            assert recs[path].new_rank == 3 and recs[path].skipped is None


def test_optimizers_must_train_every_adapted_factor():
    loss = make_sac()
    actor_opt = torch.optim.Adam(loss.actor_network_params.flatten_keys().values())
    critic_opt = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values())
    # only the actor's optimiser: the critic's Adam state would keep the old shapes and fail at its next step
    with pytest.raises(
        AdaRLValueError,
        match=r"do not train the factors of \['qvalue_network.module.mlp.0', "
        r"'qvalue_network.module.mlp.2'\].*every optimizer",
    ):
        RankAdapter(loss, actor_opt, FixedRank(3), interval=1)
    RankAdapter(loss, actor_opt, FixedRank(3), interval=1, scope="actor")  # what it trains is what it adapts
    adapter = RankAdapter(loss, [actor_opt, critic_opt], FixedRank(3), interval=1)
    adapter.optimizers = [actor_opt]  # changed after construction: refused at the event, before any change
    with pytest.raises(AdaRLValueError, match="do not train"):
        adapter.adapt()
    assert adapter.ranks[Q_L1] == 16 and adapter.history == []


def test_integer_arguments_accept_numpy_integers():
    np = pytest.importorskip("numpy")
    loss = make_sac()
    opt = torch.optim.Adam(loss.parameters())
    adapter = RankAdapter(loss, opt, FixedRank(3), interval=np.int64(2), min_rank=np.int32(1), num_threads=np.int64(1))
    assert type(adapter.interval) is int and adapter.interval == 2
    for kwargs in ({"interval": 2.0}, {"interval": 1.5}, {"interval": 2, "min_rank": 1.0}):
        with pytest.raises(AdaRLValueError, match="integer"):
            RankAdapter(loss, opt, FixedRank(3), **kwargs)
