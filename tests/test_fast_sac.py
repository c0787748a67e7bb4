"""The fused SAC update computes what TorchRL's SACLoss + Adam + SoftUpdate compute (fp tolerance)."""

from __future__ import annotations

import copy
import re

import pytest
import torch
from _helpers import BUILT, filled_sac
from torchrl.objectives import ValueEstimators

from adarl.baselines.parseval import ParsevalRegularizer
from adarl.errors import AdaRLValueError
from adarl.fast.adam import make_adam
from adarl.fast.sac import FusedSACUpdate, wants_fused
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.update import FusedStep, LossStep


@pytest.fixture(scope="module")
def filled():
    return filled_sac()


def _grads(params):
    return [None if p.grad is None else p.grad.clone() for p in params]


def _params(loss):
    return (
        [loss.log_alpha]
        + list(loss.actor_network_params.flatten_keys().values())
        + list(loss.qvalue_network_params.flatten_keys().values())
    )


def _fused_losses(fu, batch):
    """The five outputs of one fused step's losses, with the gradients left in ``.grad`` (either backward)."""
    obs, act, rew, nobs, term = fu.batch_tensors(batch)
    args = (obs, act, rew, nobs, term.bool(), *fu.draw_noise(obs, act))
    if fu.backward == "manual":
        return fu._manual(*args)
    out = fu.losses(*args)
    (out[0] + out[1] + out[2]).backward()
    return out


#: settings the fused update must compute exactly as SACLoss does (each builds its own networks and env)
CONFIGS = {
    "quickstart": [],
    # truncated ranks: the low-rank layers stay factored (x W2^T W1^T) instead of merged
    "truncated-ranks": ["network.actor.rank=4", "network.critic.rank=3"],
    # other activations and critic losses
    "tanh-elu-smooth_l1": [
        "network.actor.activation=tanh",
        "network.critic.activation=elu",
        "algorithm.loss_function=smooth_l1",
    ],
    "gelu-softplus-l1": [
        "network.actor.activation=gelu",
        "network.critic.activation=softplus",
        "algorithm.loss_function=l1",
    ],
    # an action box other than [-1, 1] (InvertedPendulum: [-3, 3]): the affine squashing
    "box-3": ["env.id=InvertedPendulum-v5", "env.perturbation.preset=none", "network.actor.rank=1"],
}


@pytest.mark.parametrize("config", CONFIGS)
def test_losses_and_gradients_match_sacloss(config):
    """Both backwards (hand-written and autograd) give SACLoss's five outputs and its gradients on the same batch
    and RNG state, over activations, critic losses, action boxes and truncated ranks."""
    overrides = CONFIGS[config]
    c = build_sac_components(load_recipe("quickstart", [*BUILT, "algorithm.fused=false", *overrides]))
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(120, break_when_any_done=False).reshape(-1))
    loss = c.modules.loss
    with torch.no_grad():
        loss.log_alpha.fill_(-1.3)  # a non-trivial alpha and alpha loss
        for p in loss.target_qvalue_network_params.flatten_keys().values():
            p.add_(0.01 * torch.randn_like(p))  # targets differ from the online critics
    batch = c.replay_buffer.sample()
    params = _params(loss)
    for p in params:
        p.grad = None
    torch.manual_seed(11)
    ref = loss(batch.clone())
    (ref["loss_actor"] + ref["loss_qvalue"] + ref["loss_alpha"]).backward()
    ref_grads = _grads(params)
    assert float(ref["loss_alpha"].detach()) != 0.0
    for backward in ("manual", "autograd"):
        for p in params:
            p.grad = None
        fu = FusedSACUpdate(loss, [], tau=0.005, backward=backward)
        assert fu.backward == backward
        torch.manual_seed(11)
        out = _fused_losses(fu, batch)
        for name, value in zip(["loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy"], out):
            torch.testing.assert_close(
                value.detach(), ref[name].detach(), rtol=1e-5, atol=1e-6, msg=f"{backward}: {name}"
            )
        for g, r in zip(_grads(params), ref_grads):
            assert g is not None and r is not None
            torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-6, msg=backward)
        if config == "truncated-ranks" and backward == "manual":
            assert any(layer.kind == "factored" for layer in fu._manual.actor.prepare(128, 64, 64))
    for p in params:
        p.grad = None
    c.close()


@pytest.mark.parametrize(
    "change, named",
    [
        (lambda loss: loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.99, lmbda=0.95), "TDLambdaEstimator"),
        (
            lambda loss: loss.make_value_estimator(ValueEstimators.TD0, gamma=0.99, average_rewards=True),
            "average_rewards=True",
        ),
        (lambda loss: setattr(loss, "reduction", "sum"), "reduction='sum'"),
        (lambda loss: setattr(loss, "skip_done_states", True), "skip_done_states=True"),
        (lambda loss: loss.set_keys(action="act"), "loss.tensor_keys.action='act'"),
        (lambda loss: loss.actor_network.module[1].distribution_kwargs.update(tanh_loc=True), "tanh_loc=True"),
    ],
    ids=["td-lambda", "average-rewards", "reduction-sum", "skip-done-states", "action-key", "tanh-loc"],
)
def test_fused_update_refuses_what_it_does_not_implement(filled, change, named):
    """A SACLoss setting the fused update would silently compute otherwise is refused, naming the setting."""
    loss = copy.deepcopy(filled[0].modules.loss)
    change(loss)
    with pytest.raises(AdaRLValueError, match=re.escape(named) + ".*algorithm.fused: false"):
        FusedSACUpdate(loss, [], tau=0.005)


def test_fused_update_reads_the_losss_tensordict_keys(filled):
    """Renamed reward and terminated keys are read where SACLoss reads them (its value estimator's tensor_keys)."""
    c, batch = filled
    loss = copy.deepcopy(c.modules.loss)
    loss.set_keys(reward="rew", terminated="term")
    renamed = batch.clone()
    renamed.rename_key_(("next", "reward"), ("next", "rew"))
    renamed.rename_key_(("next", "terminated"), ("next", "term"))
    fu = FusedSACUpdate(loss, [], tau=0.005, backward="manual")
    assert fu.keys == ("observation", "action", ("next", "rew"), ("next", "observation"), ("next", "term"))
    torch.manual_seed(11)
    ref = loss(renamed.clone())
    torch.manual_seed(11)
    out = _fused_losses(fu, renamed)
    for name, value in zip(["loss_actor", "loss_qvalue", "loss_alpha"], out):
        torch.testing.assert_close(value.detach(), ref[name].detach(), rtol=1e-5, atol=1e-6, msg=name)
    for p in _params(loss):
        p.grad = None


def _snapshot(loss):
    keys = ["actor_network_params", "qvalue_network_params", "target_qvalue_network_params"]
    return {k: getattr(loss, k).flatten_keys().clone() for k in keys} | {"log_alpha": loss.log_alpha.detach().clone()}


def _restore(loss, start) -> None:
    """Put a :func:`_snapshot` back into the loss's own tensors (in place: the update holds them)."""
    with torch.no_grad():
        for k in ("actor_network_params", "qvalue_network_params", "target_qvalue_network_params"):
            getattr(loss, k).flatten_keys().apply(lambda x: x).update_(start[k])
        loss.log_alpha.copy_(start["log_alpha"])


def _adams(loss, fused: bool) -> list:
    """Adam for the actor, the critics and alpha, as the recipes make them (for-loop or fused)."""
    return [
        make_adam(list(loss.actor_network_params.flatten_keys().values()), 3e-3, fused=fused),
        make_adam(list(loss.qvalue_network_params.flatten_keys().values()), 3e-3, fused=fused),
        make_adam([loss.log_alpha], 3e-4, fused=fused),
    ]


def _plain_steps(c, batch, n: int, terms: dict | None = None) -> list:
    """``n`` steps of TorchRL's path by hand: SACLoss (+ terms), for-loop Adam with clipping at 1, SoftUpdate; the
    terms' values."""
    loss, opts, values = c.modules.loss, _adams(c.modules.loss, False), []
    for _ in range(n):
        td = loss(batch.clone())
        for term in (terms or {}).values():
            td = term.wrap_output(td)
            values.append(td["loss_parseval"].detach())
        sum(v for k, v in td.items() if k.startswith("loss_")).backward()
        for o in opts:
            for g in o.param_groups:
                torch.nn.utils.clip_grad_norm_(g["params"], 1.0)
            o.step()
            o.zero_grad(set_to_none=True)
        c.modules.target_updater.step()
    return values


@pytest.mark.parametrize("parseval", [False, True], ids=["sac", "parseval"])
@pytest.mark.parametrize("backward", ["manual", "autograd"])
def test_full_step_matches_plain_step(filled, backward, parseval):
    """Two steps: SACLoss + for-loop Adam + clipping + SoftUpdate vs fused update + fused Adam + foreach lerp; with
    a parameter-only loss term (Parseval, strong enough to move the step) added on both paths."""
    c, batch = filled
    loss = c.modules.loss
    start = _snapshot(loss)
    terms = {"parseval": ParsevalRegularizer(loss, lam=1e-2)} if parseval else {}

    torch.manual_seed(5)
    plain_terms = _plain_steps(c, batch, 2, terms)
    plain = _snapshot(loss)

    _restore(loss, start)
    fu = FusedSACUpdate(loss, _adams(loss, True), tau=0.005, max_grad_norm=1.0, backward=backward, terms=terms)
    torch.manual_seed(5)
    fused_terms = [fu(batch).get("loss_parseval") for _ in range(2)]
    fused = _snapshot(loss)
    _restore(loss, start)
    for k in plain:
        torch.testing.assert_close(fused[k], plain[k], rtol=1e-4, atol=1e-6, msg=k)
    assert not torch.equal(plain["log_alpha"], start["log_alpha"])  # the step did move things
    if parseval:
        torch.testing.assert_close(torch.stack(fused_terms), torch.stack(plain_terms))
        # the term moved the step: without it the parameters end elsewhere
        fu = FusedSACUpdate(loss, _adams(loss, True), tau=0.005, max_grad_norm=1.0, backward=backward)
        torch.manual_seed(5)
        for _ in range(2):
            fu(batch)
        without = _snapshot(loss)
        _restore(loss, start)
        key = "module.0.module.0.0.w1"  # the actor's first (low-rank) layer
        assert not torch.allclose(without["actor_network_params"][key], fused["actor_network_params"][key])


def test_the_sparsification_layer_runs_on_the_fused_update_as_sacloss_computes_it():
    """Tiwari et al.'s layer (1024 units, k-winners-take-all; baselines/hopper_sparse): the recipe now trains on the
    fused update (autograd backward: the hand-written one refuses the layer by name), whose losses and gradients on
    one batch, and whose parameters, targets and alpha after three steps (Adam, clipping, Polyak), are SACLoss's."""
    c = build_sac_components(load_recipe("baselines/hopper_sparse", [*BUILT, "algorithm.fused=false"]))
    assert isinstance(c.update, LossStep)
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(300, break_when_any_done=False).reshape(-1))
    loss = c.modules.loss
    with torch.no_grad():
        loss.log_alpha.fill_(-1.3)
        for p in loss.target_qvalue_network_params.flatten_keys().values():
            p.add_(0.01 * torch.randn_like(p))
    with pytest.raises(AdaRLValueError, match="layer SparsificationLayer .*autograd backward"):
        FusedSACUpdate(loss, [], tau=0.005, backward="manual")
    batch = c.replay_buffer.sample()
    params = _params(loss)
    torch.manual_seed(11)
    ref = loss(batch.clone())
    (ref["loss_actor"] + ref["loss_qvalue"] + ref["loss_alpha"]).backward()
    ref_grads = _grads(params)
    for p in params:
        p.grad = None
    fu = FusedSACUpdate(loss, [], tau=0.005)
    assert fu.backward == "autograd"
    torch.manual_seed(11)
    out = _fused_losses(fu, batch)
    for name, value in zip(["loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy"], out):
        torch.testing.assert_close(value.detach(), ref[name].detach(), rtol=1e-5, atol=1e-6, msg=name)
    for g, r in zip(_grads(params), ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-6)
    for p in params:
        p.grad = None
    # three whole steps each way from the same start
    start = _snapshot(loss)
    torch.manual_seed(5)
    _plain_steps(c, batch, 3)
    plain = _snapshot(loss)
    _restore(loss, start)
    fu = FusedSACUpdate(loss, _adams(loss, True), tau=0.005, max_grad_norm=1.0)
    torch.manual_seed(5)
    for _ in range(3):
        fu(batch)
    fused = _snapshot(loss)
    for k in plain:
        torch.testing.assert_close(fused[k], plain[k], rtol=1e-4, atol=1e-6, msg=k)
    moved = plain["actor_network_params"]["module.0.module.0.2.0.weight"]  # the sparse layer's weight
    assert not torch.equal(moved, start["actor_network_params"]["module.0.module.0.2.0.weight"])
    c.close()
    # the recipe as shipped ('auto') takes the fused update
    c = build_sac_components(load_recipe("baselines/hopper_sparse", list(BUILT)))
    assert isinstance(c.update, FusedStep) and c.update.fused.backward == "autograd"
    c.close()


def test_fused_update_refuses_a_loss_term_that_reads_the_batch(filled):
    c, _ = filled

    class BatchTerm(torch.nn.Module):  # no reads_batch = False: it may read the batch
        def wrap_output(self, td):
            return td

    with pytest.raises(AdaRLValueError, match="'batchy' .*BatchTerm.* does not say so"):
        FusedSACUpdate(c.modules.loss, [], tau=0.005, terms={"batchy": BatchTerm()})


def test_a_parseval_recipe_keeps_the_fused_update():
    """algorithm.parseval on the quickstart networks: the update is the fused step and logs loss_parseval."""
    recipe = load_recipe("quickstart", [*BUILT, "algorithm.parseval.enabled=true"])
    c = build_sac_components(recipe)
    assert isinstance(c.update, FusedStep)
    c.replay_buffer.extend(c.env.rollout(100, break_when_any_done=False).reshape(-1))
    out = c.update()
    assert out["loss_parseval"].item() > 0 and {"loss_actor", "loss_qvalue", "loss_alpha"} <= set(out)
    c.close()


@pytest.mark.parametrize("backward", ["manual", "autograd"])
def test_compiled_update_recompiles_once_per_rank_event(filled, backward):
    """Shapes change at each event: the rebuilt function compiles once, results stay equal to eager."""
    c, batch = filled
    loss = copy.deepcopy(c.modules.loss)
    from torch._dynamo.utils import counters

    eager = FusedSACUpdate(loss, [], tau=0.005, backward=backward)
    compiled = FusedSACUpdate(loss, [], tau=0.005, compile=True, compile_backend="aot_eager", backward=backward)
    obs, act, rew, nobs, term = eager.batch_tensors(batch)
    noise = eager.draw_noise(obs, act)
    args = (obs, act, rew, nobs, term.bool(), *noise)

    def outputs(fu, fn):
        if backward == "autograd":
            return [t.detach() for t in fn(*args)]
        with torch.no_grad():  # the manual step's outputs and gradients (by parameter key)
            *out, grads = fn(*args)
        return out + [grads[k] for k in sorted(grads)]

    layer = loss.qvalue_network.module[2]
    key = "module.2"
    frames_before = counters["stats"]["unique_graphs"]
    for rank in (40, 30, 20, 12, 10, 9, 8, 7, 6, 5):  # more events than dynamo's default recompile limit (8)
        with torch.no_grad():
            for name in ("w1", "w2"):
                p = loss.qvalue_network_params.flatten_keys()[f"{key}.{name}"]
                t = loss.target_qvalue_network_params.flatten_keys()[f"{key}.{name}"]
                new = p.data[:, :, :rank] if name == "w1" else p.data[:, :rank, :]
                p.data = new.clone()
                t.data = new.clone()
        compiled.on_rank_event()
        if backward == "manual":
            out_c, out_e = outputs(compiled, compiled._manual._fn), outputs(eager, eager._manual.compute)
        else:
            out_c, out_e = outputs(compiled, compiled._fn), outputs(eager, eager.losses)
        assert len(out_c) == len(out_e) > 4
        for a, b in zip(out_c, out_e):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert layer is not None
    assert compiled.compilations == 11  # the first build plus one per event
    assert counters["stats"]["unique_graphs"] - frames_before >= 10  # every event compiled (no eager fall-back)


def test_fused_setting_resolution(filled):
    c, _ = filled
    assert wants_fused("auto", c.modules.loss) is True
    assert wants_fused(False, c.modules.loss) is False


def test_discrete_sac_auto_uses_plain_path_and_true_is_an_error():
    recipe = load_recipe("cartpole_adarl", ["collector.total_frames=1000", "collector.init_random_frames=250"])
    c = build_sac_components(recipe)
    assert isinstance(c.update, LossStep)
    with pytest.raises(AdaRLValueError, match="algorithm.fused"):
        wants_fused(True, c.modules.loss)


def test_compile_without_fused_is_a_recipe_error():
    with pytest.raises(ValueError, match="algorithm.compile"):
        load_recipe("quickstart", ["algorithm.fused=false", "algorithm.compile=true"])


def test_memmap_storage_and_threads(tmp_path):
    recipe = load_recipe("quickstart", [*BUILT, "replay.storage=memmap", "algorithm.num_threads=1"])
    before = torch.get_num_threads()
    try:
        c = build_sac_components(recipe, scratch_dir=tmp_path / "rb")
        assert torch.get_num_threads() == 1
        c.replay_buffer.extend(c.env.rollout(20, break_when_any_done=False).reshape(-1))
        assert type(c.replay_buffer.storage).__name__ == "LazyMemmapStorage"
        assert any((tmp_path / "rb").rglob("*.memmap"))
        assert isinstance(c.update, FusedStep)
        c.update.fused(c.replay_buffer.sample())
    finally:
        torch.set_num_threads(before)


def test_prepared_layers_merge_near_full_rank_with_the_same_output_and_gradients():
    # one update reuses a merged W1 W2 across passes; it must equal the factored product (values and grads)
    from torch import nn

    from adarl.core.lowrank import low_rank_mlp
    from adarl.fast.sac import _StackedMLP

    torch.manual_seed(0)
    net = low_rank_mlp(5, 3, (32, 32), low_rank_layers=[0, 1])
    params = {k: p.detach().clone().requires_grad_(True) for k, p in net.named_parameters(prefix="module")}
    mlp = _StackedMLP(net, params, what="actor")
    x = torch.randn(256, 5)
    merged = mlp.prepare(params, rows=256)  # 32 x 32 at full rank, 256 rows: merged
    factored = mlp.prepare(params, rows=1)  # one row: factored
    assert [k for k, _, _ in merged if k != "act"] == ["linear", "linear", "linear"]  # both products merged
    assert [k for k, _, _ in factored if k != "act"] == ["lowrank", "lowrank", "linear"]
    outs, grads = [], []
    for prepared in (merged, factored):
        y = _StackedMLP.forward(prepared, x)
        y.square().sum().backward()
        outs.append(y.detach())
        grads.append({k: p.grad.clone() for k, p in params.items()})
        for p in params.values():
            p.grad = None
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-5, atol=1e-5)
    for k in params:
        torch.testing.assert_close(grads[0][k], grads[1][k], rtol=1e-4, atol=1e-5, msg=k)
    assert isinstance(net, nn.Sequential)
    detached = _StackedMLP.detached(merged)
    assert all(not (w.requires_grad if isinstance(w, torch.Tensor) else False) for k, w, _ in detached if k != "act")


def test_uniform_tensor_sampler_draws_what_the_buffer_draws(filled):
    from adarl.fast.replay import UniformTensorSampler

    c, _ = filled
    rb, gen = c.replay_buffer, c.sampling_generator
    keys = FusedSACUpdate(c.modules.loss, [], tau=0.005).keys  # the loss's own keys
    assert keys == ("observation", "action", ("next", "reward"), ("next", "observation"), ("next", "terminated"))
    sampler = UniformTensorSampler(rb, keys, generator=gen)
    state = gen.get_state()
    ref = rb.sample()
    after = gen.get_state()
    gen.set_state(state)
    got = sampler()
    assert torch.equal(gen.get_state(), after)  # the same RNG consumption: exact resume is unchanged
    for key, t in zip(keys, got):
        assert torch.equal(ref.get(key), t), key


def test_uniform_tensor_sampler_rejects_buffers_it_cannot_reproduce():
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer

    from adarl.fast.replay import UniformTensorSampler

    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), sampler=SamplerWithoutReplacement(), batch_size=4)
    with pytest.raises(AdaRLValueError, match="RandomSampler"):
        UniformTensorSampler(rb, ["observation"])
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=4)
    sampler = UniformTensorSampler(rb, ["observation", "nope"])
    with pytest.raises(AdaRLValueError, match="empty"):
        sampler()
    rb.extend(TensorDict({"observation": torch.zeros(3, 2)}, [3]))
    with pytest.raises(AdaRLValueError, match="nope"):
        sampler()


def test_direct_adam_step_is_bit_identical_to_fused_adam_and_falls_back():
    from adarl.fast.adam import DirectAdamStep

    torch.manual_seed(0)
    ref = [torch.nn.Parameter(torch.randn(5, 3)), torch.nn.Parameter(torch.randn(3))]
    new = [torch.nn.Parameter(p.detach().clone()) for p in ref]
    opt_ref = torch.optim.Adam(ref, lr=1e-2, fused=True, weight_decay=0.01)
    opt_new = torch.optim.Adam(new, lr=1e-2, fused=True, weight_decay=0.01)
    direct = DirectAdamStep(opt_new)
    for k in range(8):
        grads = [torch.randn_like(p) for p in ref]
        for p, q, g in zip(ref, new, grads):
            p.grad, q.grad = g.clone(), g.clone()
        if k == 3:  # an LR schedule moves the rate; a rank event pops one factor's state
            opt_ref.param_groups[0]["lr"] = opt_new.param_groups[0]["lr"] = 3e-3
            opt_ref.state.pop(ref[0])
            opt_new.state.pop(new[0])
        opt_ref.step()
        opt_ref.zero_grad(set_to_none=True)
        direct.step()
        for p, q in zip(ref, new):
            assert torch.equal(p, q), k
            assert q.grad is None
    assert 0 < direct.fast_steps < 8  # the first step and the one after the pop went through opt.step()
    for p, q in zip(ref, new):
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt_ref.state[p][key], opt_new.state[q][key])
    # a hook is honoured by falling back to opt.step()
    calls = []
    opt_new.register_step_post_hook(lambda *a: calls.append(1))
    for q in new:
        q.grad = torch.ones_like(q)
    direct.step()
    assert calls == [1]


def test_direct_adam_step_with_a_scaled_factor_group_is_bit_identical_to_fused_adam():
    """``algorithm.factor_lr_scale``: two parameter groups (their own rates), one kernel call each, as Adam does."""
    from adarl.fast.adam import DirectAdamStep, make_adam

    torch.manual_seed(1)
    dense = [torch.nn.Parameter(torch.randn(4))]
    factors = [torch.nn.Parameter(torch.randn(6, 2)), torch.nn.Parameter(torch.randn(2, 5))]
    ref = [torch.nn.Parameter(p.detach().clone()) for p in dense + factors]
    opt_ref = torch.optim.Adam([{"params": ref[:1]}, {"params": ref[1:], "lr": 1e-2 * 0.5}], lr=1e-2, fused=True)
    opt_new = make_adam(dense, 1e-2, fused=True, scaled=factors, scale=0.5)
    assert [g["lr"] for g in opt_new.param_groups] == [1e-2, 5e-3]
    direct = DirectAdamStep(opt_new)
    new = dense + factors
    for k in range(6):
        for p, q in zip(ref, new):
            g = torch.randn_like(p)
            p.grad, q.grad = g.clone(), g.clone()
        if k == 2:  # a schedule moves each group's rate; a rank event pops a factor's state
            for opt in (opt_ref, opt_new):
                opt.param_groups[1]["lr"] = 1e-3
            opt_ref.state.pop(ref[2])
            opt_new.state.pop(new[2])
        opt_ref.step()
        opt_ref.zero_grad(set_to_none=True)
        direct.step()
        for p, q in zip(ref, new):
            assert torch.equal(p, q), k
    assert direct.fast_steps >= 3
    # a scale of 1 keeps the single group the optimiser always had
    assert len(make_adam(dense, 1e-2, fused=True, scaled=factors, scale=1.0).param_groups) == 1


def test_backward_setting_is_validated(filled):
    from torch import nn

    c, _ = filled
    loss = copy.deepcopy(c.modules.loss)
    assert FusedSACUpdate(loss, [], tau=0.005).backward == "manual"  # auto: the quickstart's networks qualify
    with pytest.raises(AdaRLValueError, match="backward must be one of"):
        FusedSACUpdate(loss, [], tau=0.005, backward="numerical")
    # a network the manual backward does not know: auto falls back to autograd, 'manual' says why not
    loss.actor_network.module[0].module[0][1] = nn.ReLU(inplace=True)
    assert FusedSACUpdate(loss, [], tau=0.005).backward == "autograd"
    with pytest.raises(AdaRLValueError, match="activation ReLU.*not in place"):
        FusedSACUpdate(loss, [], tau=0.005, backward="manual")
    with pytest.raises(ValueError, match="algorithm.backward"):
        load_recipe("quickstart", ["algorithm.fused=false", "algorithm.backward=manual"])
    with pytest.raises(ValueError, match="algorithm.backward"):
        load_recipe("quickstart", ["algorithm.backward=numeric"])


def test_manual_step_compiled_by_inductor_equals_eager(filled):
    """What ``algorithm.compile: true`` runs: the manual step compiled by inductor (fused C++ kernels)."""
    c, batch = filled
    loss = copy.deepcopy(c.modules.loss)
    eager = FusedSACUpdate(loss, [], tau=0.005, backward="manual")
    compiled = FusedSACUpdate(loss, [], tau=0.005, backward="manual", compile=True)
    obs, act, rew, nobs, term = eager.batch_tensors(batch)
    args = (obs, act, rew, nobs, term.bool(), *eager.draw_noise(obs, act))
    with torch.no_grad():
        *out_e, grads_e = eager._manual.compute(*args)
        *out_c, grads_c = compiled._manual._fn(*args)
    assert sorted(grads_c) == sorted(grads_e) and compiled.compilations == 1
    for a, b in zip(out_c + [grads_c[k] for k in sorted(grads_c)], out_e + [grads_e[k] for k in sorted(grads_e)]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
