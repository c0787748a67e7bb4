"""The sparsification layer's sparse form computes the dense form's function and gradients (adarl.baselines.sparse):
outputs and the gradient of every parameter (exact zeros included) on several batch shapes, under ties at the
k-th unit, under ``torch.vmap`` over stacked parameters (TorchRL's critic ensemble) and other functorch transforms,
without a graph, through TorchScript / ``torch.export``, and one SAC update of the ``baselines/hopper_sparse``
recipe on TorchRL's ``SACLoss`` path."""

from __future__ import annotations

import copy

import pytest
import torch
from _helpers import BUILT
from tensordict import TensorDict
from torch import nn
from torch.func import functional_call, grad, stack_module_state, vmap

from adarl.baselines import DiagonalScale, SparsificationLayer, make_baseline_mlp, sparse
from adarl.baselines.sparse import FORMS, KWinnersTakeAll, set_form, winners
from adarl.errors import AdaRLValueError

# the sparse form reorders sums (k terms instead of width, index_add_ instead of a matmul): fp32 rounding only
TOL = {"rtol": 1e-5, "atol": 1e-6}


@pytest.fixture(autouse=True)
def sparse_at_any_batch(monkeypatch):
    """The sparse form at every batch size (it hands inputs of fewer than 32 rows to the dense form)."""
    monkeypatch.setattr(sparse, "_MIN_ROWS", 1)
    calls = []
    apply = sparse._SparseReLULinear.apply
    monkeypatch.setattr(sparse._SparseReLULinear, "apply", lambda *a: calls.append(1) or apply(*a))
    return calls


def _net(in_features=11, out=3, width=1024, k=7, seed=0):
    torch.manual_seed(seed)
    return make_baseline_mlp(in_features, out, [64, 64], sparse_layer=1, sparse_width=width, sparse_k=k)


def _run(net, x, form, upstream_seed=1):
    """Output, input gradient and every parameter's gradient under a random upstream gradient."""
    set_form(net, form)
    net.zero_grad(set_to_none=True)
    x = x.detach().clone().requires_grad_(True)
    y = net(x)
    g = torch.randn(y.shape, generator=torch.Generator().manual_seed(upstream_seed))
    (y * g).sum().backward()
    return y.detach(), x.grad, {n: p.grad.clone() for n, p in net.named_parameters()}


def _assert_same(dense, fast):
    y_d, gx_d, g_d = dense
    y_s, gx_s, g_s = fast
    torch.testing.assert_close(y_s, y_d, **TOL)
    torch.testing.assert_close(gx_s, gx_d, **TOL)
    assert g_d.keys() == g_s.keys()
    for name in g_d:
        torch.testing.assert_close(g_s[name], g_d[name], **TOL, msg=name)
        # the rows (units) that get no gradient in the dense form get exactly none in the sparse form
        assert torch.equal(g_s[name] == 0, g_d[name] == 0), name


@pytest.mark.parametrize("shape", [(100,), (3, 5), (1,), ()])
def test_sparse_form_equals_dense_form(shape, sparse_at_any_batch):
    net = _net()
    x = torch.randn(*shape, 11)
    dense = _run(net, x, "dense")
    assert not sparse_at_any_batch
    fast = _run(net, x, "sparse")
    assert sparse_at_any_batch  # the sparse form ran
    _assert_same(dense, fast)
    assert torch.equal(fast[0], dense[0])  # the same matmul, gathered: the outputs are the dense form's bits
    wide = fast[2]["2.0.weight"]  # the 1024 x 64 layer
    rows = int((wide.abs().sum(-1) > 0).sum())
    assert 0 < rows <= 7 * max(1, int(torch.tensor(shape).prod())) and rows < 1024  # only winners' rows


def test_one_observation_at_a_time_runs_the_dense_form(monkeypatch, sparse_at_any_batch):
    monkeypatch.setattr(sparse, "_MIN_ROWS", 32)
    net = _net()
    with torch.no_grad():
        one, many = net(torch.randn(11)), net(torch.randn(31, 11))
    assert not sparse_at_any_batch and one.shape == (3,) and many.shape == (31, 3)
    net(torch.randn(32, 11))
    assert sparse_at_any_batch


def test_forms_switch_and_are_checked():
    net = _net()
    layer = next(m for m in net.modules() if isinstance(m, SparsificationLayer))
    assert layer.form == "sparse" and FORMS == ("sparse", "dense")
    assert set_form([net, net], "dense") == 1 and layer.form == "dense"
    with pytest.raises(AdaRLValueError, match="form must be one of"):
        set_form(net, "fast")
    with pytest.raises(AdaRLValueError, match="form must be one of"):
        SparsificationLayer(4, 8, 2, form="fast")


def _tied_net(mixed: bool):
    """A layer whose units 2, 3 and 4 share their weights and bias: they tie at every input, at rank 3 (k = 3)
    behind the large units 0 and 1, so the dense form keeps 5 units. ``mixed``: unit 5 overtakes the tied group
    for some inputs only (rows differ in how many units they keep)."""
    torch.manual_seed(3)
    layer = SparsificationLayer(4, width=16, k=3)
    with torch.no_grad():
        w, b = layer[0].weight, layer[0].bias
        w.mul_(0.1)
        b.fill_(-5.0)
        b[:2] = 10.0
        w[3:5] = w[2]
        b[2:5] = 2.0
        if mixed:
            w[5].zero_()
            w[5, 0] = 4.0
            b[5] = 2.0
    return nn.Sequential(layer, nn.Linear(16, 2))


@pytest.mark.parametrize("mixed", [False, True])
def test_ties_at_the_kth_unit_keep_every_tied_unit_in_both_forms(mixed):
    net = _tied_net(mixed)
    x = torch.randn(64, 4)
    layer = net[0]
    with torch.no_grad():
        dense_h = nn.Sequential(*list(layer))(x)
    kept = (dense_h != 0).sum(-1)
    assert int(kept.max()) == 5  # the tie crosses the k-th unit: more than k units survive
    if mixed:
        assert int(kept.min()) < 5  # ... but not in every row
    _assert_same(_run(net, x, "dense"), _run(net, x, "sparse"))
    # the same under vmap (the rows split over the vmapped dimension: the tie check sees them all at once)
    outs = {}
    for form in ("dense", "sparse"):
        set_form(net, form)
        xx = x.view(4, 16, 4).clone().requires_grad_(True)
        y = vmap(net)(xx)
        (y * torch.linspace(-1, 1, y.numel()).view(y.shape)).sum().backward()
        outs[form] = (y.detach(), xx.grad)
    torch.testing.assert_close(outs["sparse"][0], outs["dense"][0], **TOL)
    torch.testing.assert_close(outs["sparse"][1], outs["dense"][1], **TOL)


def test_fewer_positive_units_than_k_is_no_tie():
    torch.manual_seed(4)
    layer = SparsificationLayer(4, width=32, k=7)
    with torch.no_grad():
        layer[0].bias.fill_(-3.0)  # most units dead: the k-th largest ReLU output is 0
    net = nn.Sequential(layer, nn.Linear(32, 2))
    x = torch.randn(50, 4)
    with torch.no_grad():
        alive = (layer[0](x) > 0).sum(-1)
    assert int(alive.min()) < 7
    _assert_same(_run(net, x, "dense"), _run(net, x, "sparse"))


@pytest.mark.parametrize("zeros_dead", [False, True])
def test_winners_are_exactly_the_units_the_dense_mask_keeps(zeros_dead):
    torch.manual_seed(5)
    scores = torch.randint(-3, 6, (200, 40)).float()  # a few values over 40 units: ties everywhere
    index, values, keep = winners(scores, 6, zeros_dead=zeros_dead)
    assert keep is not None  # ties crossed the k-th unit
    chosen = torch.zeros_like(scores, dtype=torch.bool).scatter_(-1, index, keep)
    kth = scores.topk(6, dim=-1).values[..., -1:]
    want = scores >= kth
    if zeros_dead:
        want &= scores > 0
    assert torch.equal(chosen, want)
    assert torch.equal(values, scores.gather(-1, index))
    distinct = torch.randn(20, 40)
    index, values, keep = winners(distinct, 6)
    assert keep is None and index.shape == (20, 6)
    assert torch.equal(values, distinct.topk(6, dim=-1).values)


def _stacked(n=2, seed=0):
    models = [_net(in_features=14, out=1, seed=seed + i) for i in range(n)]
    params, _ = stack_module_state(models)
    base = copy.deepcopy(models[0]).to("meta")
    return base, params


@pytest.mark.parametrize("batched_input", [False, True])
def test_vmap_over_stacked_parameters_as_sacloss_runs_the_critics(batched_input, sparse_at_any_batch):
    base, params = _stacked()
    x = torch.randn(2, 100, 14) if batched_input else torch.randn(100, 14)
    results = {}
    for form in ("dense", "sparse"):
        set_form(base, form)
        ps = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
        xx = x.clone().requires_grad_(True)
        y = vmap(lambda p, i: functional_call(base, p, (i,)), (0, 0 if batched_input else None))(ps, xx)
        (y * torch.linspace(-1, 1, y.numel()).view(y.shape)).sum().backward()
        results[form] = (y.detach(), xx.grad, {k: v.grad for k, v in ps.items()})
    _assert_same(results["dense"], results["sparse"])
    assert sparse_at_any_batch


def test_vmap_over_inputs_with_shared_parameters_and_nested_vmap(sparse_at_any_batch):
    net = _net(in_features=5, out=2, width=64, k=4)
    x = torch.randn(3, 4, 10, 5)
    results = {}
    for form in ("dense", "sparse"):
        set_form(net, form)
        net.zero_grad(set_to_none=True)
        xx = x.clone().requires_grad_(True)
        y = vmap(vmap(net))(xx)
        (y * torch.linspace(-1, 1, y.numel()).view(y.shape)).sum().backward()
        results[form] = (y.detach(), xx.grad, {n: p.grad.clone() for n, p in net.named_parameters()})
    _assert_same(results["dense"], results["sparse"])
    # nested, the parameters stacked at the outer level only: an ensemble of networks over a batch of batches
    base, params = _stacked(n=3)
    x = torch.randn(4, 10, 14)
    outs = {}
    for form in ("dense", "sparse"):
        set_form(base, form)
        outs[form] = vmap(lambda p: vmap(lambda i: functional_call(base, p, (i,)))(x))(params)
    torch.testing.assert_close(outs["sparse"], outs["dense"], **TOL)
    assert sparse_at_any_batch


def test_other_transforms_get_the_dense_form(sparse_at_any_batch):
    net = _net(in_features=5, out=1, width=64, k=4)
    x = torch.randn(5)
    set_form(net, "sparse")
    g_sparse = grad(lambda i: net(i).sum())(x)
    set_form(net, "dense")
    g_dense = grad(lambda i: net(i).sum())(x)
    torch.testing.assert_close(g_sparse, g_dense, **TOL)
    assert not sparse_at_any_batch


def test_without_a_graph_and_in_inference_mode():
    net = _net()
    x = torch.randn(32, 11)
    set_form(net, "dense")
    with torch.no_grad():
        want = net(x)
    set_form(net, "sparse")
    with torch.no_grad():
        assert torch.equal(net(x), want)
    with torch.inference_mode():
        assert torch.equal(net(x), want)


def test_layouts_the_sparse_form_does_not_compute_run_the_dense_form():
    """Another activation, a DiagonalScale inside the layer, k >= width: the module's own chain, unchanged."""
    torch.manual_seed(6)
    x = torch.randn(8, 4)
    tanh = SparsificationLayer(4, width=16, k=3, activation=nn.Tanh)
    assert not tanh._sparse_form_applies()
    diag = SparsificationLayer(4, width=16, k=3)
    diag.insert(1, DiagonalScale(16))
    assert not diag._sparse_form_applies()
    full = SparsificationLayer(4, width=16, k=16)
    assert not full._sparse_form_applies()
    for layer in (tanh, diag, full):
        want = x
        for m in layer:
            want = m(want)
        assert torch.equal(layer(x), want)
    assert diag.k == 3  # the k-WTA module is the last one, wherever a DiagonalScale sits


def test_scripted_and_exported_layers_are_the_dense_form(monkeypatch):
    monkeypatch.setattr(sparse, "_MIN_ROWS", 32)  # as shipped: the batch-size test must not reach torch.export
    layer = SparsificationLayer(8, width=64, k=5)
    x = torch.randn(40, 8)
    want = layer(x)
    scripted = torch.jit.script(copy.deepcopy(layer).eval())
    assert torch.equal(scripted(x), want)
    batch = {0: torch.export.Dim("batch")}  # as adarl.runtime.export exports a policy
    exported = torch.export.export(copy.deepcopy(layer).eval().requires_grad_(False), (x,), dynamic_shapes=(batch,))
    assert torch.equal(exported.module()(x), want)
    assert torch.equal(exported.module()(x[:3]), layer(x[:3]))
    assert isinstance(layer[-1], KWinnersTakeAll)


# ------------------------------------------------------------------------------ one SAC update, TorchRL's path


def _components():
    from adarl.runtime.builders.sac import build_sac_components
    from adarl.runtime.config import load_recipe

    # TorchRL's SACLoss path (the critics under torch.vmap); the fused update's is tests/test_fast_sac.py's
    c = build_sac_components(load_recipe("baselines/hopper_sparse", [*BUILT, "algorithm.fused=false"]))
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(200, break_when_any_done=False).reshape(-1))
    return c


def _params(loss) -> dict[str, torch.Tensor]:
    out = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
    out.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items()})
    out.update({f"target.{k}": v for k, v in loss.target_qvalue_network_params.flatten_keys(".").items()})
    return {k: v.detach().clone() for k, v in out.items()}


def test_one_sac_update_of_the_sparse_recipe_equals_the_dense_form(sparse_at_any_batch):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from adarl.runtime.update import LossStep

    sides = {form: _components() for form in ("dense", "sparse")}
    for form, c in sides.items():
        loss = c.modules.loss
        assert isinstance(c.update, LossStep)  # TorchRL's SACLoss: the critics run under torch.vmap
        assert set_form((loss.actor_network, loss.qvalue_network), form) == 2  # actor and critic
    start = [_params(c.modules.loss) for c in sides.values()]
    for k in start[0]:
        assert torch.equal(start[0][k], start[1][k]), k  # the same seed builds the same networks

    # the gradients of one loss evaluation, every parameter (the wide layers' unused rows exactly zero)
    grads = {}
    batches = {form: c.replay_buffer.sample() for form, c in sides.items()}  # each side's sampler moves alike
    assert (batches["dense"] == batches["sparse"]).all()
    for form, c in sides.items():
        loss = c.modules.loss
        torch.manual_seed(11)
        td = loss(batches[form])
        (td["loss_actor"] + td["loss_qvalue"] + td["loss_alpha"]).backward()
        named = {f"actor.{k}": v for k, v in loss.actor_network_params.flatten_keys(".").items()}
        named.update({f"critic.{k}": v for k, v in loss.qvalue_network_params.flatten_keys(".").items()})
        grads[form] = {k: v.grad.clone() for k, v in named.items() if v.grad is not None}
        for o in c.optimizers.values():
            o.zero_grad(set_to_none=True)
    assert grads["dense"].keys() == grads["sparse"].keys() and len(grads["dense"]) >= 10
    assert len(sparse_at_any_batch) == 5  # actor twice, the critics thrice (vmapped): the sparse form
    for k, g in grads["dense"].items():
        torch.testing.assert_close(grads["sparse"][k], g, rtol=1e-4, atol=1e-6, msg=k)
        assert torch.equal(grads["sparse"][k] == 0, g == 0), k

    # whole updates (replay sample, losses, backward, Adam, Polyak), the same RNG on both sides
    for i in range(3):
        for c in sides.values():
            torch.manual_seed(100 + i)
            c.update(update=i)
    after = {form: _params(c.modules.loss) for form, c in sides.items()}
    for k, v in after["dense"].items():
        torch.testing.assert_close(after["sparse"][k], v, rtol=1e-4, atol=1e-6, msg=k)
    wide = "actor.module.0.module.0.2.0.weight"  # the actor's 1024 x 64 layer
    assert start[0][wide].shape == (1024, 64) and not torch.equal(after["dense"][wide], start[0][wide])

    # the deterministic (evaluation) action
    obs = batches["dense"]["observation"][:16]
    actions = {}
    for form, c in sides.items():
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            actions[form] = c.modules.actor(TensorDict({"observation": obs}, [16]))["action"]
    torch.testing.assert_close(actions["sparse"], actions["dense"], rtol=1e-4, atol=1e-6)
    for c in sides.values():
        c.close()


def _argpartition_calls(monkeypatch) -> list:
    """Count numpy's selection inside :func:`adarl.baselines.sparse.largest` (so that no test below compares
    ``topk`` with itself)."""
    calls, argpartition = [], sparse.np.argpartition
    monkeypatch.setattr(sparse.np, "argpartition", lambda *a, **kw: calls.append(1) or argpartition(*a, **kw))
    return calls


@pytest.mark.parametrize(
    "shape, m, dtype",
    [((256, 1024), 18, torch.float32), ((2, 64, 1024), 36, torch.float32), ((7, 300), 9, torch.float64)],
)
def test_largest_is_topk_where_numpy_selects(shape, m, dtype, monkeypatch):
    calls = _argpartition_calls(monkeypatch)
    x = torch.randn(shape, dtype=dtype, generator=torch.Generator().manual_seed(0))
    for scores in (x, x.transpose(0, -2).contiguous().transpose(0, -2)):  # and a non-contiguous layout
        values, index = sparse.largest(scores, m)
        want_values, want_index = scores.topk(m, dim=-1)
        assert index.dtype == torch.long and values.dtype == dtype
        assert torch.equal(values, want_values) and torch.equal(index, want_index)  # untied: the same units
    assert len(calls) == 2


def test_largest_under_ties_nan_and_infinities(monkeypatch):
    calls = _argpartition_calls(monkeypatch)
    gen = torch.Generator().manual_seed(1)
    scores = torch.randint(-4, 5, (300, 100), generator=gen).float()  # ties everywhere, across the m-th too
    scores[0, 3] = float("nan")
    scores[1, :50] = float("-inf")
    scores[2, 7] = float("inf")
    scores[3:, :] += torch.arange(100) * 1e-3  # rows 3-99 without ties; rows 100- tie among the 9 or at the 9th
    scores[100:200, :] = torch.randn(100, 100, generator=gen)
    scores[100:200, 40:60] = 9.0  # twenty units tie among the 9 largest
    scores[200:, 40:42] = scores[200:].amax(-1, keepdim=True) + 1.0  # two tie above the rest ...
    top10 = scores[200:].topk(10, dim=-1)
    scores[200:].scatter_(-1, top10.indices[:, 9:], top10.values[:, 8:9])  # ... and the 10th unit at the 9th value
    values, index = sparse.largest(scores, 9)
    want, want_index = scores.topk(9, dim=-1)
    torch.testing.assert_close(values, want, rtol=0, atol=0, equal_nan=True)  # NaN first, as topk has it
    # tied units in topk's order; where the 9th value recurs outside the nine, the 9th unit is one of that value
    assert torch.equal(index[:, :8], want_index[:, :8])
    boundary = (scores >= want[:, -1:]).sum(-1) > 9
    assert torch.equal(index[~boundary], want_index[~boundary]) and bool(boundary[200:].all())
    torch.testing.assert_close(scores.gather(-1, index), values, rtol=0, atol=0, equal_nan=True)
    assert all(len(set(row.tolist())) == 9 for row in index)  # nine distinct units a row
    assert len(calls) == 1


def test_largest_keeps_topk_where_it_is_fast_or_numpy_cannot_help(monkeypatch):
    calls = _argpartition_calls(monkeypatch)
    x = torch.randn(64, 1024)
    sparse.largest(x, 8)  # the heap's range (64 m <= n), Hopper's k + 1
    sparse.largest(x, 1024)  # all units
    sparse.largest(x.requires_grad_(True), 36)  # a graph to keep
    sparse.largest(x.detach().bfloat16(), 36)  # numpy has no bfloat16
    vmap(lambda row: sparse.largest(row, 36))(x.detach())  # under a transform
    assert not calls


@pytest.mark.parametrize("k", [17, 35])  # Ant's and Humanoid's 2 d_a + 1
def test_the_sparse_form_is_bit_for_bit_the_same_with_numpys_selection(k, monkeypatch):
    calls = _argpartition_calls(monkeypatch)
    net, x = _net(k=k), torch.randn(256, 11)
    fast = _run(net, x, "sparse")
    assert calls
    with monkeypatch.context() as m:
        m.setattr(sparse, "largest", lambda s, n: s.topk(n, dim=-1))
        slow = _run(net, x, "sparse")
    assert torch.equal(fast[0], slow[0]) and torch.equal(fast[1], slow[1])
    assert all(torch.equal(fast[2][name], slow[2][name]) for name in slow[2])


def test_fused_updates_of_a_humanoid_width_k_are_bit_for_bit_the_same_with_numpys_selection(monkeypatch):
    """Three whole fused updates (the recipes' path: the critics stacked, Adam, Polyak) with k = 35, the same
    batches: every parameter bit for bit the same whether ``largest`` selects with numpy or with ``topk``."""
    from adarl.runtime.builders.sac import build_sac_components
    from adarl.runtime.config import load_recipe
    from adarl.runtime.update import FusedStep

    calls = _argpartition_calls(monkeypatch)
    overrides = [*BUILT, "network.actor.sparse.k=35", "network.critic.sparse.k=35"]
    sides = {}
    for side in ("numpy", "topk"):
        c = build_sac_components(load_recipe("baselines/hopper_sparse", overrides))
        assert isinstance(c.update, FusedStep)
        torch.manual_seed(3)
        c.replay_buffer.extend(c.env.rollout(300, break_when_any_done=False).reshape(-1))
        sides[side] = c
    start = _params(sides["numpy"].modules.loss)
    with monkeypatch.context() as m:
        for side, c in sides.items():
            if side == "topk":
                m.setattr(sparse, "largest", lambda s, n: s.topk(n, dim=-1))
            for i in range(3):
                torch.manual_seed(100 + i)
                c.update(update=i)
    assert calls
    after = {side: _params(c.modules.loss) for side, c in sides.items()}
    for name, value in after["topk"].items():
        assert torch.equal(after["numpy"][name], value), name
    moved = [name for name, value in start.items() if not torch.equal(after["numpy"][name], value)]
    assert len(moved) >= 10, moved  # the updates changed the networks (actor, critics, targets)
    for c in sides.values():
        c.close()
