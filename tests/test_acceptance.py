"""Algorithm 1's acceptance step: a rule's candidate rank is applied only if the truncated network still fits.

Each test here fails on the literal ratchet (every candidate applied), the behaviour before the acceptance step.
"""

import math

import pytest
import torch
from tensordict import TensorDict
from test_adapter import ACTOR_L0, ACTOR_L1, Q_L0, Q_L1, fake_batch, make_sac, train
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer
from torchrl.data.replay_buffers.writers import TensorDictMaxValueWriter

from adarl import ProjectionAcceptance, RankAdapter, RecentTransitions, recent_transitions
from adarl.core.adapter import find_low_rank_layers
from adarl.core.rank import EnergyRule
from adarl.errors import AdaRLValueError


def _set_spectrum(site, singular_values, seed=0):
    """Give a (single-network) site the weight U diag(s) V^T with random orthonormal U, V (balanced factors)."""
    g = torch.Generator().manual_seed(seed)
    out, width = site.w1.shape[-2], site.w1.shape[-1]
    inp = site.w2.shape[-1]
    u = torch.linalg.qr(torch.randn(out, width, generator=g, dtype=torch.float64))[0]
    v = torch.linalg.qr(torch.randn(inp, width, generator=g, dtype=torch.float64))[0]
    s = torch.as_tensor(singular_values, dtype=torch.float64)
    with torch.no_grad():
        site.w1.copy_((u * s.sqrt()).to(site.w1.dtype))
        site.w2.copy_((s.sqrt()[:, None] * v.T).to(site.w2.dtype))


def _site(loss, path):
    return next(s for s in find_low_rank_layers(loss)[0] if s.path == path)


def _concentrated_actor(seed=0):
    """An SAC loss whose actor hidden layer has exact rank 3 (+ a 1e-4 tail): it needs 3 directions, no more."""
    loss = make_sac(seed)
    site = _site(loss, ACTOR_L1)
    _set_spectrum(site, [3.0, 2.0, 1.5] + [1e-4] * 13, seed)
    return loss


def _ranks_over_events(loss, acceptance, events=14):
    opt = torch.optim.Adam(loss.parameters())
    batch = fake_batch(seed=11, n=512)
    adapter = RankAdapter(
        loss, opt, EnergyRule(0.98), interval=1, scope="actor", acceptance=acceptance, fit_data=lambda: batch
    )
    return [adapter.adapt() for _ in range(events)], adapter


def test_a_concentrated_layer_settles_and_stops_moving():
    events, adapter = _ranks_over_events(_concentrated_actor(), ProjectionAcceptance())
    ranks = [next(r.new_rank for r in e.layers if r.layer == ACTOR_L1) for e in events]
    assert ranks[0] == 3, ranks  # the 1e-4 tail goes at once (its removal changes nothing)
    assert all(r == 3 for r in ranks), ranks  # ... and the three directions the layer needs stay
    last = next(r for r in events[-1].layers if r.layer == ACTOR_L1)
    assert last.candidate == 2 and last.candidate_error > last.tolerance == 0.05
    assert "kept rank 3" in last.skipped
    # The literal ratchet (every candidate applied) takes the same layer down to rank 1.
    literal, _ = _ranks_over_events(_concentrated_actor(), None)
    lit = [next(r.new_rank for r in e.layers if r.layer == ACTOR_L1) for e in literal]
    assert lit[-1] == 1 and lit[0] < 3, lit


def test_a_damaging_candidate_is_refused():
    loss = make_sac(1)
    site = _site(loss, ACTOR_L1)
    _set_spectrum(site, [1.0] * 16)  # flat: every direction carries as much as any other
    opt = torch.optim.Adam(loss.parameters())
    batch = fake_batch(seed=2, n=512)
    adapter = RankAdapter(
        loss,
        opt,
        EnergyRule(0.98),
        interval=1,
        scope="actor",
        acceptance=ProjectionAcceptance(actor_tol=0.01, search=False),
        fit_data=lambda: batch,
    )
    rec = next(r for r in adapter.adapt().layers if r.layer == ACTOR_L1)
    assert rec.candidate == 15 and rec.new_rank == rec.old_rank == 16  # Eq. 10 proposed r - 1; refused
    assert rec.candidate_error > 0.01 and rec.error == 0.0 and rec.tolerance == 0.01
    assert "tolerance" in rec.skipped and site.rank == 16
    # the literal rule applies it anyway, and records the damage (with layer 0's truncation in place before it)
    literal = RankAdapter(loss, opt, EnergyRule(0.98), interval=1, scope="actor", fit_data=lambda: batch)
    lit = next(r for r in literal.adapt().layers if r.layer == ACTOR_L1)
    assert lit.new_rank == 15 and lit.tolerance is None and lit.error >= rec.candidate_error > 0.01


def test_the_default_never_takes_a_layer_that_needs_more_to_rank_one():
    # Many events with training in between: the layer that needs three directions keeps at least three.
    loss = _concentrated_actor(3)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    batch = fake_batch(seed=4, n=512)
    adapter = RankAdapter(
        loss, opt, EnergyRule(0.98), interval=2, acceptance=ProjectionAcceptance(), fit_data=lambda: batch
    )
    train(loss, opt, steps=40, adapter=adapter, seed=100)
    assert len(adapter.history) == 20
    assert adapter.ranks[ACTOR_L1] >= 3
    assert all(r >= 2 for r in adapter.ranks.values()), adapter.ranks


def test_records_show_candidate_error_and_tolerance_for_actor_and_critic():
    loss = make_sac(2)
    opt = torch.optim.Adam(loss.parameters())
    train(loss, opt, steps=2)
    batch = fake_batch(seed=5, n=256)
    acc = ProjectionAcceptance(actor_tol=0.07, critic_tol=0.03)
    adapter = RankAdapter(loss, opt, EnergyRule(0.98), interval=1, acceptance=acc, fit_data=lambda: batch)
    event = adapter.adapt()
    recs = {r.layer: r for r in event.layers}
    assert set(recs) == {ACTOR_L0, ACTOR_L1, Q_L0, Q_L1}
    for r in recs.values():
        assert r.candidate is not None and r.candidate < r.old_rank
        assert r.candidate_error is not None and math.isfinite(r.candidate_error)
        assert r.tolerance == (0.07 if r.network == "actor" else 0.03)
        assert r.tried and r.tried[0][0] == r.candidate
        assert r.error <= r.tolerance
        if r.new_rank == r.candidate:
            assert r.error == r.candidate_error and r.note is None
        elif r.new_rank < r.old_rank:
            assert r.candidate_error > r.tolerance and "within it" in r.note
        else:
            assert r.error == 0.0 and r.skipped
    d = event.as_dict()["layers"][2]
    assert {"candidate", "candidate_error", "error", "tolerance", "tried", "note"} <= set(d)
    train(loss, opt, steps=2)  # training goes on after the event


def test_layers_of_one_network_share_the_tolerance():
    """Decided in order with earlier truncations in place: the accepted network is within tol of the old one."""
    loss = make_sac(4)
    opt = torch.optim.Adam(loss.parameters())
    batch = fake_batch(seed=6, n=512)
    reference = None
    from adarl.core.adapter import _NetworkProbe

    site = _site(loss, ACTOR_L0)
    reference = _NetworkProbe("actor_network", site.network, site.params, (), batch)
    adapter = RankAdapter(
        loss,
        opt,
        EnergyRule(0.5),
        interval=1,
        scope="actor",
        acceptance=ProjectionAcceptance(actor_tol=0.2),
        fit_data=lambda: batch,
    )
    event = adapter.adapt()
    after = _NetworkProbe("actor_network", site.network, site.params, (), batch).reference
    from adarl.core.acceptance import relative_output_error

    total = relative_output_error(after, reference.reference)
    assert total <= 0.2 + 1e-6
    last = [r for r in event.layers if r.network == "actor"][-1]
    if last.new_rank < last.old_rank:  # the last layer's error is the network's error after the event
        assert total == pytest.approx(last.error, rel=1e-4)


def test_resolve_searches_the_smallest_rank_within_tolerance():
    acc = ProjectionAcceptance(actor_tol=0.05, critic_tol=0.05)
    err = lambda k: (20 - k) * 0.01  # noqa: E731  (monotone: 0.05 at rank 15)
    r = acc.resolve(2, 20, err, "actor")
    assert r.rank == 15 and r.candidate == 2 and not r.accepted and r.error == pytest.approx(0.05)
    assert r.tried[0][0] == 2 and len(r.tried) <= 6  # bisection: log2(18) measurements after the candidate
    assert ProjectionAcceptance(search=False).resolve(2, 20, err, "critic").rank == 20
    assert acc.resolve(16, 20, err, "critic").accepted
    assert acc.resolve(3, 20, lambda k: math.nan, "actor").rank == 20  # NaN is never within a tolerance
    with pytest.raises(AdaRLValueError, match="candidate"):
        acc.resolve(20, 20, err, "actor")


@pytest.mark.parametrize("kw", [{"actor_tol": -0.1}, {"critic_tol": math.inf}, {"actor_tol": True}, {"search": 1}])
def test_acceptance_validation(kw):
    with pytest.raises(AdaRLValueError):
        ProjectionAcceptance(**kw)


def test_acceptance_needs_data():
    loss = make_sac()
    with pytest.raises(AdaRLValueError, match="fit_data"):
        RankAdapter(
            loss, torch.optim.Adam(loss.parameters()), EnergyRule(0.98), interval=1, acceptance=ProjectionAcceptance()
        )
    with pytest.raises(AdaRLValueError, match="ProjectionAcceptance"):
        RankAdapter(
            loss,
            torch.optim.Adam(loss.parameters()),
            EnergyRule(0.98),
            interval=1,
            acceptance=0.05,
            fit_data=lambda: fake_batch(),
        )


def test_recent_transitions_after_an_empty_that_keeps_the_write_count():
    # ReplayWarmStart empties the buffer keeping write_count (TorchRL collectors gate their random phase on it)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    rb.extend(TensorDict({"x": torch.arange(7)}, [7]))
    rb.empty(empty_write_count=False)
    rb.extend(TensorDict({"x": torch.arange(100, 104)}, [4]))
    assert rb.write_count == 11
    assert recent_transitions(rb, 3)["x"].tolist() == [101, 102, 103]
    assert recent_transitions(rb, 50)["x"].tolist() == [100, 101, 102, 103]


def test_recent_transitions_are_the_last_written_in_order():
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    for i in range(0, 23, 4):  # 24 writes into 10 slots: wraps around twice
        rb.extend(TensorDict({"x": torch.arange(i, i + 4)}, [4]))
    assert recent_transitions(rb, 5)["x"].tolist() == [19, 20, 21, 22, 23]
    assert RecentTransitions(rb, 50)()["x"].tolist() == list(range(14, 24))  # at most what the buffer holds
    plain = ReplayBuffer(storage=LazyTensorStorage(8))
    plain.extend(TensorDict({"x": torch.arange(3)}, [3]))
    assert recent_transitions(plain, 2)["x"].tolist() == [1, 2]
    with pytest.raises(AdaRLValueError, match="empty"):
        recent_transitions(TensorDictReplayBuffer(storage=LazyTensorStorage(4)), 2)
    other = TensorDictReplayBuffer(storage=LazyTensorStorage(4), writer=TensorDictMaxValueWriter(rank_key="x"))
    with pytest.raises(AdaRLValueError, match="RoundRobinWriter"):
        recent_transitions(other, 2)
    with pytest.raises(AdaRLValueError, match="n must"):
        RecentTransitions(rb, 0)


@pytest.mark.parametrize("functional", [True, False])
def test_on_policy_loss_measures_on_the_last_batch(functional):
    """ClipPPOLoss: no replay buffer; the acceptance step compares outputs on the batch just trained on."""
    from test_adapter_losses import make_ppo, ppo_batch_fn, run

    loss, actor, critic = make_ppo(functional)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    batches = ppo_batch_fn(loss)
    last = {"batch": batches(0)}
    adapter = RankAdapter(
        loss,
        opt,
        EnergyRule(0.98),
        interval=2,
        acceptance=ProjectionAcceptance(0.05, 0.05),
        fit_data=lambda: last["batch"],
    )

    def batch_fn(i):
        last["batch"] = batches(i)
        return last["batch"]

    events = run(loss, opt, adapter, 6, batch_fn)
    assert len(events) == 3
    for e in events:
        for r in e.layers:
            assert r.tolerance == 0.05 and r.candidate is not None and r.new_rank <= r.old_rank
            assert r.error is None or r.error <= 0.05
    assert critic.module[0].w1.shape[-1] == adapter.ranks["critic_network.module.0"]


def test_td3_critic_outputs_are_compared():
    from test_adapter_losses import QNet, transition_batch
    from torchrl.modules import Actor, ValueOperator
    from torchrl.objectives import TD3Loss, ValueEstimators

    from adarl.core.lowrank import low_rank_mlp

    torch.manual_seed(0)
    actor = Actor(low_rank_mlp(5, 2, (16, 16)), in_keys=["observation"])
    loss = TD3Loss(actor, ValueOperator(QNet(), in_keys=["observation", "action"]), bounds=(-1.0, 1.0))
    loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99)
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    batch = transition_batch(3)
    adapter = RankAdapter(
        loss, opt, EnergyRule(0.9), interval=1, acceptance=ProjectionAcceptance(0.02, 0.02), fit_data=lambda: batch
    )
    event = adapter.adapt()
    roles = {r.network for r in event.layers}
    assert roles == {"actor", "critic"}
    assert all(r.candidate_error is not None for r in event.layers if r.candidate < r.old_rank)
