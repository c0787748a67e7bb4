"""The registered initialisation schemes (recipe key ``network.<net>.init.scheme``): ``orthogonal``, as the baselines'
original code draws its layers, and ``independent_factors``, the paper's Fig. 5 bottleneck as two ``nn.Linear``.

**orthogonal.** Both originals draw every linear layer with ``torch.nn.init.orthogonal_`` and zero its bias; they
differ in the hidden layers' gain:

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

**independent_factors.** The paper inserts "an intermediate linear layer (without activation functions or bias)" into
each factorised layer (Fig. 5) and does not say how it starts. :class:`~adarl.core.lowrank.LowRankLinear`'s own init
(the best rank-``r`` factorisation of a dense ``nn.Linear`` draw, balanced: exact at full rank) is one reading; this
scheme is the one a user stacking torch modules gets: ``W2`` drawn as ``nn.Linear(in, r, bias=False).weight`` and
``W1`` as ``nn.Linear(r, out).weight``, each Kaiming-uniform at its own fan-in. The product then starts with entries of
variance ``r / (3 in) * 1 / (3 r) = 1 / (9 in)``, a third of the dense draw's ``1 / (3 in)``, and unbalanced factors.
Biases and every layer that is not factorised keep their own init; a network with no factorised layer is refused
(the scheme would do nothing). Rank events re-factorise balanced as always. Issue 45's mechanism arm (e)
(docs/reproduction.md). ``gain`` and ``head_gain`` are not used.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn

from adarl.baselines.registry import register_init
from adarl.core.lowrank import LowRankLinear, refactorize
from adarl.errors import AdaRLValueError

__all__ = [
    "linear_layers",
    "orthogonal_weight",
    "orthogonal_init_",
    "orthogonal_init_loss_",
    "independent_factors_init_",
    "independent_factors_init_loss_",
]


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

    def draw(i, n, layer, ref):
        return _draw(layer, head_gain if i == n - 1 else gain, ref.dtype, ref.device)

    return _init_loss_params_(loss, network, draw, low_rank_only=False)


def _loss_network(loss: nn.Module, network: str):
    module = getattr(loss, network, None)
    params = getattr(loss, f"{network}_params", None)
    if module is None or not isinstance(params, TensorDictBase):
        raise AdaRLValueError(f"{type(loss).__name__} has no {network} / {network}_params to initialise")
    return module, params, getattr(loss, f"target_{network}_params", None)


def _init_loss_params_(loss: nn.Module, network: str, draw: Callable, *, low_rank_only: bool) -> int:
    """Write ``draw(i, n, layer, ref)`` (a dict of fresh values by parameter name) into each member of the loss's
    parameters of the ``i``-th of the ``n`` linear layers of ``network``, then copy them into the target parameters."""
    module, params, target = _loss_network(loss, network)
    layers = linear_layers(module)
    chosen = [(i, p, m) for i, (p, m) in enumerate(layers) if isinstance(m, LowRankLinear) or not low_rank_only]
    if not chosen:
        what = "factorised (LowRankLinear)" if low_rank_only else "Linear/LowRankLinear"
        raise AdaRLValueError(f"{network} of {type(loss).__name__} has no {what} layer to initialise")
    for i, path, layer in chosen:
        key = tuple(path.split(".")) if path else ()
        names = ("w1", "w2") if isinstance(layer, LowRankLinear) else ("weight",)
        names += ("bias",) if layer.bias is not None else ()
        tensors = {n: params.get(key + (n,)) for n in names}
        ref = tensors[names[0]]
        stacked = ref.dim() == getattr(layer, names[0]).dim() + 1
        for m in range(ref.shape[0] if stacked else 1):
            for n, value in draw(i, len(layers), layer, ref).items():
                (tensors[n].data[m] if stacked else tensors[n].data).copy_(value)
        if isinstance(target, TensorDictBase):
            for n, t in tensors.items():
                tgt = target.get(key + (n,), None)
                if tgt is not None:
                    tgt.data.copy_(t.data)
    return len(chosen)


@torch.no_grad()
def _independent_factors(layer: LowRankLinear, rank: int, dtype, device) -> dict[str, torch.Tensor]:
    """``w1`` and ``w2`` of one member drawn as the bias-free ``nn.Linear`` pair would be (Kaiming-uniform,
    ``a = sqrt(5)``, at each factor's own fan-in: ``rank`` for ``w1``, ``in_features`` for ``w2``)."""
    w1 = torch.empty(layer.out_features, rank, dtype=dtype, device=device)
    w2 = torch.empty(rank, layer.in_features, dtype=dtype, device=device)
    nn.init.kaiming_uniform_(w1, a=math.sqrt(5))
    nn.init.kaiming_uniform_(w2, a=math.sqrt(5))
    return {"w1": w1, "w2": w2}


@torch.no_grad()
def independent_factors_init_(network: nn.Module, gain: float = 1.0, head_gain: float = 1.0) -> int:
    """Re-draw the factors of every :class:`~adarl.core.lowrank.LowRankLinear` of ``network`` in place, each as a
    bias-free ``nn.Linear`` of its shape would start (module docstring); biases and other layers are left as they are.
    A stacked layer's members are drawn apart. ``gain`` and ``head_gain`` are not used (the registry passes them).
    Returns how many layers were drawn."""
    del gain, head_gain
    layers = [m for _, m in linear_layers(network) if isinstance(m, LowRankLinear)]
    if not layers:
        raise AdaRLValueError(
            f"init scheme 'independent_factors' draws factorised layers, and {type(network).__name__} has none "
            "(set network.<net>.low_rank_layers, or use scheme 'default' or 'orthogonal')"
        )
    for layer in layers:
        w1, w2 = (p.data.view(-1, *p.shape[-2:]) for p in (layer.w1, layer.w2))  # members of a stacked layer
        for m1, m2 in zip(w1, w2):
            fresh = _independent_factors(layer, m1.shape[-1], m1.dtype, m1.device)
            m1.copy_(fresh["w1"])
            m2.copy_(fresh["w2"])
    return len(layers)


@torch.no_grad()
def independent_factors_init_loss_(loss: nn.Module, network: str, gain: float = 1.0, head_gain: float = 1.0) -> int:
    """:func:`independent_factors_init_` for the parameters a TorchRL loss trains for ``network``: each member of a
    stacked ensemble drawn apart, the target parameters set to the same values. Returns the layers drawn."""
    del gain, head_gain
    return _init_loss_params_(
        loss,
        network,
        lambda i, n, layer, ref: _independent_factors(layer, ref.shape[-1], ref.dtype, ref.device),
        low_rank_only=True,
    )


register_init("orthogonal", orthogonal_init_, orthogonal_init_loss_)
register_init("independent_factors", independent_factors_init_, independent_factors_init_loss_)
