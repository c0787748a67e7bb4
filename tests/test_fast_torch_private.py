"""The fast path's torch-private calls sit behind one version guard (adarl/fast/_torch_private.py): on a torch it does
not know, every caller takes its public path, computes the same update, and one warning says so."""

from __future__ import annotations

import warnings

import pytest
import torch
from _helpers import filled_sac

from adarl.errors import TorchFallbackWarning
from adarl.fast import _torch_private as private
from adarl.fast.adam import DirectAdamStep, make_adam
from adarl.fast.sac import FusedSACUpdate

KEYS = ("actor_network_params", "qvalue_network_params", "target_qvalue_network_params")


@pytest.fixture
def unknown_torch(monkeypatch):
    """The guard as it answers on a torch it was not tested on (its notice not emitted yet)."""
    monkeypatch.setattr(private, "_checked", {"reason": f"torch {torch.__version__} is forced unknown by the test"})
    monkeypatch.setattr(private, "_warned", [])


@pytest.fixture(scope="module")
def filled():
    return filled_sac()


def _snapshot(loss):
    return {k: getattr(loss, k).flatten_keys().clone() for k in KEYS} | {"log_alpha": loss.log_alpha.detach().clone()}


def _steps(loss, batch, start, n=3):
    """``n`` fused updates from ``start`` (restored first); the end state, the losses and the update."""
    with torch.no_grad():
        for k in KEYS:
            getattr(loss, k).flatten_keys().apply(lambda x: x).update_(start[k])
        loss.log_alpha.copy_(start["log_alpha"])
    opts = [
        make_adam(list(loss.actor_network_params.flatten_keys().values()), 3e-3, fused=True),
        make_adam(list(loss.qvalue_network_params.flatten_keys().values()), 3e-3, fused=True),
        make_adam([loss.log_alpha], 3e-4, fused=True),
    ]
    fu = FusedSACUpdate(loss, opts, tau=0.005, max_grad_norm=1.0, backward="auto")
    torch.manual_seed(5)
    losses = [fu(batch)["loss_qvalue"] for _ in range(n)]
    return _snapshot(loss), torch.stack(losses), fu


def test_the_known_torch_uses_the_private_calls():
    assert private.reason() is None and private.usable()
    assert private._probe() is None


def test_an_unknown_version_or_signature_is_refused(monkeypatch):
    monkeypatch.setattr(torch, "__version__", "2.99.0")
    assert "torch 2.99.0 is not a version" in private._probe()
    monkeypatch.undo()
    monkeypatch.setitem(private.SCHEMAS, "_foreach_lerp_.Scalar", "self other weight")
    assert "aten::_foreach_lerp_.Scalar has another signature" in private._probe()
    monkeypatch.setitem(private.SCHEMAS, "_no_such_op_.default", "self")
    monkeypatch.delitem(private.SCHEMAS, "_foreach_lerp_.Scalar")
    assert "has no aten::_no_such_op_.default" in private._probe()


def test_fallback_computes_the_fast_paths_update(filled, monkeypatch):
    """Three SAC updates on the fast path, then with the guard saying 'unknown torch': the fallback (public
    ``Adam.step()``, autograd, per-tensor ``lerp_``) ends at the same parameters and losses, fp tolerance."""
    c, batch = filled
    loss = c.modules.loss
    start = _snapshot(loss)
    fast, fast_losses, fu = _steps(loss, batch, start)
    assert fu.backward == "manual" and all(a.fast_steps > 0 for a in fu._adam_steps)

    monkeypatch.setattr(private, "_checked", {"reason": "forced by the test"})
    monkeypatch.setattr(private, "_warned", [])
    with pytest.warns(TorchFallbackWarning, match="forced by the test; using the public paths"):
        slow, slow_losses, fu = _steps(loss, batch, start)
    assert fu.backward == "autograd" and all(a.fast_steps == 0 for a in fu._adam_steps)
    for k in fast:
        torch.testing.assert_close(slow[k], fast[k], rtol=1e-4, atol=1e-6, msg=k)
    torch.testing.assert_close(slow_losses, fast_losses, rtol=1e-4, atol=1e-6)
    assert not torch.equal(fast["log_alpha"], start["log_alpha"])  # the updates did move things


def test_fallback_adam_is_bit_identical(unknown_torch):
    """The direct Adam step's fallback is ``Adam(fused=True).step()``: the very kernels, so the same bits."""
    torch.manual_seed(0)
    ref = [torch.nn.Parameter(torch.randn(5, 3)), torch.nn.Parameter(torch.randn(3))]
    new = [torch.nn.Parameter(p.detach().clone()) for p in ref]
    opt_ref = torch.optim.Adam(ref, lr=1e-2, fused=True)
    direct = DirectAdamStep(torch.optim.Adam(new, lr=1e-2, fused=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TorchFallbackWarning)
        for _ in range(4):
            for p, q in zip(ref, new):
                p.grad = q.grad = torch.randn_like(p)
            opt_ref.step()
            opt_ref.zero_grad(set_to_none=True)
            direct.step()
            assert all(torch.equal(p, q) and q.grad is None for p, q in zip(ref, new))
    assert direct.fast_steps == 0
    targets, sources = [torch.zeros(3), torch.ones(2)], [torch.ones(3), torch.full((2,), 3.0)]
    private.foreach_lerp_(targets, sources, 0.25)
    assert torch.equal(targets[0], torch.full((3,), 0.25)) and torch.equal(targets[1], torch.full((2,), 1.5))


def test_the_notice_is_emitted_once(unknown_torch):
    params = [torch.nn.Parameter(torch.randn(3))]
    direct = DirectAdamStep(torch.optim.Adam(params, lr=1e-2, fused=True))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            params[0].grad = torch.ones(3)
            direct.step()
        assert not private.usable() and not private.usable()
        private.foreach_lerp_([torch.zeros(1)], [torch.ones(1)], 0.5)
    notices = [w for w in caught if issubclass(w.category, TorchFallbackWarning)]
    assert len(notices) == 1
    text = str(notices[0].message)
    assert "\n" not in text and torch.__version__ in text and "using the public paths instead" in text
