"""Orthogonal initialisation as the baselines' original code does it (recipe key ``network.<net>.init``).

Both originals draw every linear layer with ``torch.nn.init.orthogonal_`` and zero its bias; they differ in the
hidden layers' gain:

* RNAC's PPO trainer (tliu1997/RNAC, ``ppo_continuous.py``): gain 1 on the hidden layers, 0.01 on the policy's
  mean head, 1 on the value head.
* Parseval regularisation (wechu/parseval_reg, ``agent.py``): gain ``sqrt(2)`` on the hidden layers, so that
  ``W W^T`` starts at ``2 I``, exactly the ``s I`` the penalty pulls towards; 0.01 policy head, 1 value head.

Why it matters: PyTorch's default ``nn.Linear`` init starts a 64x64 layer at mean ``diag(W W^T) = 1/3``, six
times below Parseval's target, so the penalty first spends its gradient on rescaling the weights; and RNAC's
0.01 head starts the policy mean at ~0 for every state.

A :class:`~adarl.core.lowrank.LowRankLinear` gets the best rank-``r`` factorisation of an orthogonal draw (exact at full
rank, balanced factors). The output layer of a network is its last linear layer, as in
:func:`adarl.baselines.parseval_weights`. TorchRL losses that keep a critic ensemble as new stacked parameters
(SACLoss resamples them uniformly within the template's range) need :func:`orthogonal_init_loss_`, which draws each
member apart and copies the result into the target parameters.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from adarl.baselines.registry import register_init
from adarl.core.lowrank import LowRankLinear, refactorize
from adarl.errors import AdaRLValueError

__all__ = ["linear_layers", "orthogonal_weight", "orthogonal_init_", "orthogonal_init_loss_"]


def linear_layers(network: nn.Module) -> list[tuple[str, nn.Module]]:
    """``(path, layer)`` of every ``nn.Linear`` / :class:`~adarl.core.lowrank.LowRankLinear` of ``network`` in module
    order; the last one is the output layer."""
    return [(p, m) for p, m in network.named_modules() if isinstance(m, (nn.Linear, LowRankLinear))]


def _check_gain(name: str, gain) -> float:
    if isinstance(gain, bool) or not isinstance(gain, (int, float)) or not gain > 0:
        raise AdaRLValueError(f"{name} must be a number > 0, got {gain!r}")
    return float(gain)


@torch.no_grad()
def orthogonal_weight(
    out_features: int, in_features: int, gain: float = 1.0, *, dtype=torch.float32, device=None
) -> torch.Tensor:
    """An ``(out, in)`` matrix drawn by ``torch.nn.init.orthogonal_``: every singular value equals ``gain``."""
    w = torch.empty(out_features, in_features, dtype=dtype, device=device)
    return nn.init.orthogonal_(w, gain=gain)


@torch.no_grad()
def _draw(layer: nn.Module, gain: float, dtype, device) -> dict[str, torch.Tensor]:
    """Fresh orthogonal values for one layer: ``weight`` or ``w1``/``w2``, and a zero ``bias``."""
    w = orthogonal_weight(layer.out_features, layer.in_features, gain, dtype=torch.float64, device=device)
    if isinstance(layer, LowRankLinear):
        u, s, vh = torch.linalg.svd(w, full_matrices=False)
        w1, w2 = refactorize(u, s, vh, layer.rank, dtype)
        out = {"w1": w1.to(device), "w2": w2.to(device)}
    else:
        out = {"weight": w.to(dtype)}
    if layer.bias is not None:
        out["bias"] = torch.zeros(layer.out_features, dtype=dtype, device=device)
    return out


@torch.no_grad()
def orthogonal_init_(network: nn.Module, gain: float = 1.0, head_gain: float = 1.0) -> int:
    """Re-draw every linear layer of ``network`` in place: orthogonal with ``gain`` (hidden layers) or
    ``head_gain`` (the last linear layer), zero biases. Returns how many layers were drawn."""
    gain, head_gain = _check_gain("gain", gain), _check_gain("head_gain", head_gain)
    layers = linear_layers(network)
    if not layers:
        raise AdaRLValueError(f"{type(network).__name__} has no Linear/LowRankLinear layer to initialise")
    for i, (_, layer) in enumerate(layers):
        ref = layer.w1 if isinstance(layer, LowRankLinear) else layer.weight
        for name, value in _draw(layer, head_gain if i == len(layers) - 1 else gain, ref.dtype, ref.device).items():
            getattr(layer, name).copy_(value)
    return len(layers)


@torch.no_grad()
def orthogonal_init_loss_(loss: nn.Module, network: str, gain: float = 1.0, head_gain: float = 1.0) -> int:
    """:func:`orthogonal_init_` for the parameters a TorchRL loss trains for ``network`` (e.g. ``"actor_network"``,
    ``"qvalue_network"``): each member of a stacked ``[n, ...]`` ensemble is drawn apart, and the loss's target
    parameters (``target_<network>_params``), if any, are set to the same values. Returns the layers drawn."""
    gain, head_gain = _check_gain("gain", gain), _check_gain("head_gain", head_gain)
    module = getattr(loss, network, None)
    params = getattr(loss, f"{network}_params", None)
    if module is None or not isinstance(params, TensorDictBase):
        raise AdaRLValueError(f"{type(loss).__name__} has no {network} / {network}_params to initialise")
    target = getattr(loss, f"target_{network}_params", None)
    layers = linear_layers(module)
    if not layers:
        raise AdaRLValueError(f"{network} of {type(loss).__name__} has no Linear/LowRankLinear layer to initialise")
    for i, (path, layer) in enumerate(layers):
        key = tuple(path.split(".")) if path else ()
        names = ("w1", "w2") if isinstance(layer, LowRankLinear) else ("weight",)
        names += ("bias",) if layer.bias is not None else ()
        tensors = {n: params.get(key + (n,)) for n in names}
        ref = tensors[names[0]]
        stacked = ref.dim() == getattr(layer, names[0]).dim() + 1
        members = ref.shape[0] if stacked else 1
        g = head_gain if i == len(layers) - 1 else gain
        for m in range(members):
            for n, value in _draw(layer, g, ref.dtype, ref.device).items():
                (tensors[n].data[m] if stacked else tensors[n].data).copy_(value)
        if isinstance(target, TensorDictBase):
            for n, t in tensors.items():
                tgt = target.get(key + (n,), None)
                if tgt is not None:
                    tgt.data.copy_(t.data)
    return len(layers)


register_init("orthogonal", orthogonal_init_, orthogonal_init_loss_)
