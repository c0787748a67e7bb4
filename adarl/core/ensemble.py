"""The members of a TorchRL Q ensemble whose layers are low-rank: each drawn with LowRankLinear's own init.

Why a fix is needed: a TorchRL loss builds its ensemble by resampling every stacked parameter uniformly between the
template's extremes, which for factor pairs starts the product far larger (and worse conditioned) than a dense
layer's init. A component fix on stock TorchRL, hence in core; the SAC builder calls it after building the loss.
"""

from __future__ import annotations

import torch

from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLValueError

__all__ = ["reinit_low_rank_ensemble"]


@torch.no_grad()
def reinit_low_rank_ensemble(loss, network: str = "qvalue_network") -> int:
    """Give every member of a TorchRL Q ensemble's low-rank layers :class:`LowRankLinear`'s own initialisation.

    Why: a TorchRL loss builds its ensemble (``num_qvalue_nets`` copies, ``expand_dim`` in
    ``LossModule.convert_to_functional``) by resampling every stacked parameter uniformly in ``[min, max]`` of the
    template's values. For a dense ``nn.Linear`` that is its own init distribution; for the factors ``W1``, ``W2``
    it is not: the product of two independent uniform factors starts ~2-5x larger than ``nn.Linear`` (64 wide)
    and with its condition number squared. This redraws each member's ``w1``, ``w2`` and bias as a fresh
    ``LowRankLinear`` (a factorised ``nn.Linear`` init) and copies them into the target parameters. Call it right
    after building the loss (``make_sac_loss`` does). Returns how many layers were redrawn.
    """
    params = getattr(loss, f"{network}_params", None)
    module = getattr(loss, network, None)
    if params is None or module is None:
        raise AdaRLValueError(f"{type(loss).__name__} has no {network}_params to re-initialise")
    online = dict(params.flatten_keys(".").items())
    target = getattr(loss, f"target_{network}_params", None)
    target = dict(target.flatten_keys(".").items()) if target is not None else {}
    count = 0
    for name, layer in module.named_modules():
        if not isinstance(layer, LowRankLinear):
            continue
        keys = [f"{name}.{p}" for p in ("w1", "w2", "bias") if getattr(layer, p, None) is not None]
        if not all(k in online for k in keys):
            continue
        members = online[keys[0]].shape[0] if online[keys[0]].dim() == 3 else None
        if members is None:  # not stacked: the layer kept its own init
            continue
        device, dtype = online[keys[0]].device, online[keys[0]].dtype
        for i in range(members):
            fresh = LowRankLinear(
                layer.in_features,
                layer.out_features,
                rank=layer.rank,
                bias=layer.bias is not None,
                device=device,
                dtype=dtype,
            )
            for k, p in zip(keys, ("w1", "w2", "bias")):
                online[k].data[i].copy_(getattr(fresh, p))
        for k in keys:
            if k in target:
                target[k].data.copy_(online[k].data)
        count += 1
    return count
