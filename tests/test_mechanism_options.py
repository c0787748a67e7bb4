"""Issue 45's mechanism options, each where it acts: ``algorithm.polyak: product`` (the target critics' factorised
layers follow the averaged product) and ``algorithm.factor_lr_scale`` (the factors' Adam rate), on both update
paths (the fused step and TorchRL's SACLoss + SoftUpdate), through a rank event; and
``network.<net>.init.scheme: independent_factors`` (arm (e): the factors drawn apart, as Fig. 5's bottleneck)."""

from __future__ import annotations

import pytest
import torch
from _helpers import BUILT

from adarl.baselines import independent_factors_init_
from adarl.core.lowrank import LowRankLinear
from adarl.core.product_polyak import ProductSoftUpdate, averaged_factors, factor_pairs, product_polyak_
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.update import FusedStep, LossStep


def _filled(overrides):
    c = build_sac_components(load_recipe("quickstart", [*BUILT, *overrides]))
    torch.manual_seed(3)
    c.replay_buffer.extend(c.env.rollout(200, break_when_any_done=False).reshape(-1))
    with torch.no_grad():
        for p in c.modules.loss.target_qvalue_network_params.flatten_keys().values():
            p.add_(0.05 * torch.randn_like(p))  # targets differ from the online critics
    return c


def _flat(td):
    return dict(td.flatten_keys(".").items())


def _pairs(loss):
    return factor_pairs(_flat(loss.target_qvalue_network_params), _flat(loss.qvalue_network_params))


@pytest.mark.parametrize("fused", [True, False])
def test_product_polyak_moves_the_target_product_to_the_averaged_product(fused):
    c = _filled(["algorithm.polyak=product", f"algorithm.fused={str(fused).lower()}"])
    loss, tau = c.modules.loss, c.recipe.algorithm.tau
    assert isinstance(c.update, FusedStep if fused else LossStep)
    if not fused:
        assert isinstance(c.modules.target_updater, ProductSoftUpdate)
    pairs = _pairs(loss)
    assert len(pairs) == 2  # the critic's two factorised layers (stacked over the two critics)
    before = [(tw1.clone() @ tw2.clone(), tw1.clone(), tw2.clone()) for tw1, tw2, _, _ in pairs]
    dense_before = {k: v.clone() for k, v in _flat(loss.target_qvalue_network_params).items() if "w" not in k[-2:]}
    c.update(update=0)
    for (tw1, tw2, w1, w2), (product, _, _) in zip(pairs, before):
        want = (1 - tau) * product.double() + tau * (w1.double() @ w2.double())
        r = tw1.shape[-1]
        s = torch.linalg.svdvals(want)
        err = torch.linalg.matrix_norm(tw1.double() @ tw2.double() - want)
        # the best rank-r approximation of the averaged product (exact at full rank), balanced factors
        torch.testing.assert_close(err, s[..., r:].pow(2).sum(-1).sqrt(), atol=2e-5, rtol=0)
        torch.testing.assert_close(tw1.norm(dim=-2), tw2.norm(dim=-1), atol=1e-4, rtol=1e-4)
    # the biases still follow TorchRL's per-tensor Polyak average
    online = _flat(loss.qvalue_network_params)
    for k, old in dense_before.items():
        if k.endswith("bias"):
            torch.testing.assert_close(_flat(loss.target_qvalue_network_params)[k], old.lerp(online[k], tau))
    # 'factors' (the default) is not this: the per-factor average's product differs from the averaged product
    tw1, tw2, w1, w2 = (t.clone() for t in pairs[1])
    per_factor = tw1.lerp(w1, tau) @ tw2.lerp(w2, tau)
    a, b = averaged_factors((tw1, tw2, w1, w2), tau)
    assert not torch.allclose(per_factor, a @ b, atol=1e-6)


def test_product_polyak_fused_and_torchrl_paths_agree_through_a_rank_event():
    """Same recipe, seed and RNG: the two paths' target critics agree after updates, a truncation by the real
    adapter (the target factors synced at the new rank, then averaged there) and more updates."""
    common = ["algorithm.polyak=product", "rank.rule=fixed", "rank.target_rank=5", "rank.accept.mode=always"]
    sides = [_filled(common + [f"algorithm.fused={f}"]) for f in ("true", "false")]
    for phase in (range(5), range(5, 10)):
        for c in sides:
            for i in phase:
                torch.manual_seed(100 + i)
                c.update(update=i)
        if phase[0] == 0:
            ranks = [[r.new_rank for r in c.adapter.adapt().layers] for c in sides]
            assert ranks[0] == ranks[1] and 5 in ranks[0]
    ta, tb = (_flat(c.modules.loss.target_qvalue_network_params) for c in sides)
    assert ta.keys() == tb.keys()
    for k in ta:
        assert ta[k].shape == tb[k].shape, k
        torch.testing.assert_close(ta[k], tb[k], atol=1e-4, rtol=1e-3, msg=k)


def test_product_polyak_keeps_a_diverged_member_non_finite():
    g = torch.Generator().manual_seed(0)
    t = [torch.randn(2, 8, 8, generator=g), torch.randn(2, 8, 8, generator=g)]
    o = [torch.randn(2, 8, 8, generator=g), torch.randn(2, 8, 8, generator=g)]
    o[0][1, 0, 0] = float("nan")
    product_polyak_([(*t, *o)], tau=0.005)
    assert torch.isfinite(t[0][0]).all() and not torch.isfinite(t[0][1]).all()


@pytest.mark.parametrize("fused", [True, False])
def test_factor_lr_scale_puts_the_factors_in_a_scaled_group(fused):
    sides = {
        scale: _filled([f"algorithm.fused={str(fused).lower()}", f"algorithm.factor_lr_scale={scale}"])
        for scale in (1.0, 0.5)
    }
    c = sides[0.5]
    lr = c.recipe.algorithm.lr
    assert len(sides[1.0].optimizers["actor"].param_groups) == 1
    for name in ("actor", "critic"):
        groups = c.optimizers[name].param_groups
        assert [g["initial_lr"] for g in groups] == pytest.approx([lr, 0.5 * lr]), name
        ids = {id(p) for p in groups[1]["params"]}
        flat = _flat(getattr(c.modules.loss, f"{'actor' if name == 'actor' else 'qvalue'}_network_params"))
        assert ids == {id(v) for k, v in flat.items() if k.endswith(("w1", "w2"))}
        assert c.schedulers[name].base_lrs == pytest.approx([lr, 0.5 * lr])
    # the warm-up's first rate is 0, so the second update's gradients are the same on both sides: there, Adam's
    # step on a factor is exactly half the unscaled one, and every other parameter's step is the same
    before = {scale: {k: v.detach().clone() for k, v in _params(s).items()} for scale, s in sides.items()}
    for s in sides.values():
        for i in range(2):
            torch.manual_seed(7 + i)
            s.update(update=i)
    steps = {scale: {k: v.detach() - before[scale][k] for k, v in _params(s).items()} for scale, s in sides.items()}
    for k, full in steps[1.0].items():
        half = steps[0.5][k]
        want = 0.5 * full if k.endswith(("w1", "w2")) else full
        assert full.abs().max() > 0, k
        torch.testing.assert_close(half, want, rtol=0, atol=1e-7, msg=k)  # float32 rounding of the parameters (~0.3)


def _params(c):
    loss = c.modules.loss
    named = {f"actor.{k}": v for k, v in _flat(loss.actor_network_params).items()}
    named.update({f"critic.{k}": v for k, v in _flat(loss.qvalue_network_params).items()})
    return named


@pytest.mark.parametrize(
    "override, message",
    [
        (["algorithm.polyak=average"], "algorithm.polyak"),
        (["algorithm.factor_lr_scale=0"], "algorithm.factor_lr_scale"),
        (["algorithm.name=td3", "algorithm.polyak=product"], "implemented for SAC"),
        (["algorithm.name=td3", "algorithm.factor_lr_scale=0.8"], "implemented for SAC"),
        (["network.critic.low_rank_layers=[]", "network.critic.init.scheme=independent_factors"], "low_rank_layers is"),
        (["network.actor.init.scheme=kaiming"], "independent_factors"),
    ],
)
def test_mechanism_options_are_validated(override, message):
    with pytest.raises(ValueError, match=message):
        load_recipe("quickstart", override)


def _factor_layers(loss, network):
    """``{path: (w1, w2, bias)}`` of the loss's parameters of ``network``'s factorised layers (stacked members kept)."""
    flat = _flat(getattr(loss, f"{network}_params"))
    return {
        k[: -len(".w1")]: (v, flat[k[:-1] + "2"], flat[k[: -len("w1")] + "bias"])
        for k, v in flat.items()
        if k.endswith("w1")
    }


def test_independent_factors_draws_each_factor_as_a_bias_free_linear():
    """Arm (e): W2 as nn.Linear(in, r, bias=False), W1 as nn.Linear(r, out) start (Kaiming-uniform at each factor's
    fan-in), every critic member apart and the targets equal to them; biases and unfactorised layers as the default
    scheme draws them, so that the arm differs from its base in the factors alone."""
    scheme = ["network.actor.init.scheme=independent_factors", "network.critic.init.scheme=independent_factors"]
    built = {
        name: build_sac_components(load_recipe("quickstart", [*BUILT, *o]))
        for name, o in (("default", []), ("independent", scheme))
    }
    loss = {name: c.modules.loss for name, c in built.items()}
    for network in ("actor_network", "qvalue_network"):
        layers = {name: _factor_layers(l, network) for name, l in loss.items()}
        assert layers["default"].keys() == layers["independent"].keys() and len(layers["default"]) == 2, network
        for path, (w1, w2, bias) in layers["independent"].items():
            d1, d2, dbias = layers["default"][path]
            rank, fan_in = w1.shape[-1], w2.shape[-1]
            for w, bound in ((w1, rank**-0.5), (w2, fan_in**-0.5)):
                assert w.abs().max() <= bound
                # uniform on [-bound, bound]: std bound / sqrt(3), here within a few % (>= 700 entries)
                assert w.std().item() == pytest.approx(bound / 3**0.5, rel=0.12), (network, path)
            torch.testing.assert_close(bias, dbias)  # the layer's own bias draw, untouched
            for a, b, da, db in zip(
                w1.view(-1, *w1.shape[-2:]),
                w2.view(-1, *w2.shape[-2:]),
                d1.view(-1, *d1.shape[-2:]),
                d2.view(-1, *d2.shape[-2:]),
            ):
                # the default's factors are balanced (W1^T W1 = W2 W2^T = S); drawn apart they are not
                torch.testing.assert_close(da.T @ da, db @ db.T, atol=1e-4, rtol=1e-4)
                assert (a.T @ a - b @ b.T).abs().max() > 0.1
                # the product: entries of variance 1 / (9 in) against the dense draw's 1 / (3 in)
                assert (a @ b).std().item() == pytest.approx((9 * fan_in) ** -0.5, rel=0.2)
                assert (da @ db).std().item() == pytest.approx((3 * fan_in) ** -0.5, rel=0.2)
            if w1.dim() == 3:  # the twin critics drawn apart, and the targets start equal to them
                assert not torch.equal(w1[0], w1[1])
                target = _flat(loss["independent"].target_qvalue_network_params)
                torch.testing.assert_close(target[f"{path}.w1"], w1, rtol=0, atol=0)
                torch.testing.assert_close(target[f"{path}.w2"], w2, rtol=0, atol=0)
        # every parameter of a layer that is not factorised is the default scheme's
        flat = {name: _flat(getattr(l, f"{network}_params")) for name, l in loss.items()}
        others = [k for k in flat["default"] if not any(k.startswith(p + ".") for p in layers["default"])]
        assert others
        for k in others:
            torch.testing.assert_close(flat["independent"][k], flat["default"][k], rtol=0, atol=0, msg=k)
    # the actor the collector runs is the loss's actor: the drawn factors are what it acts with
    actor = built["independent"].modules.actor
    factored = [m for m in actor.modules() if isinstance(m, LowRankLinear)]
    assert factored and all(
        any(torch.equal(m.w1, w1) for w1, _, _ in _factor_layers(loss["independent"], "actor_network").values())
        for m in factored
    )


def test_independent_factors_on_a_module_draws_stacked_members_apart_and_refuses_a_dense_network():
    layer = LowRankLinear(14, 64, rank=14)
    layer.w1.data = layer.w1.data.expand(3, -1, -1).clone()
    layer.w2.data = layer.w2.data.expand(3, -1, -1).clone()
    bias = layer.bias.detach().clone()
    assert independent_factors_init_(torch.nn.Sequential(layer, torch.nn.ReLU())) == 1
    assert not torch.equal(layer.w1[0], layer.w1[1]) and not torch.equal(layer.w2[1], layer.w2[2])
    assert layer.w1.abs().max() <= 14**-0.5 and layer.w2.abs().max() <= 14**-0.5
    torch.testing.assert_close(layer.bias, bias, rtol=0, atol=0)
    with pytest.raises(ValueError, match="has none"):
        independent_factors_init_(torch.nn.Sequential(torch.nn.Linear(3, 4)))
