"""Polyak averaging of a factorised layer's product, not of its factors (``algorithm.polyak: product``).

TorchRL's :class:`~torchrl.objectives.SoftUpdate` averages every tensor on its own. For a low-rank layer
``W = W1 W2`` that averages ``W1`` and ``W2`` separately, and the target product
``((1 - tau) W1' + tau W1) ((1 - tau) W2' + tau W2)`` is not the average of the online products: it carries a
cross term ``tau (1 - tau) (W1' W2 + W1 W2')`` and depends on how the factors are balanced. Here the target
layer follows ``(1 - tau) W1' W2' + tau W1 W2`` instead, re-factorised at the layer's rank (the balanced split of
its best rank-``r`` approximation, as a rank event does); at full rank that is exactly the averaged product. The
paper leaves the choice open; issue 45 measures it as a mechanism arm.

>>> import torch
>>> g = torch.Generator().manual_seed(0)
>>> online = (torch.randn(2, 6, 5, generator=g), torch.randn(2, 5, 5, generator=g))  # full rank: 5 = min(6, 5)
>>> target = (torch.randn(2, 6, 5, generator=g), torch.randn(2, 5, 5, generator=g))
>>> want = 0.9 * target[0] @ target[1] + 0.1 * online[0] @ online[1]
>>> product_polyak_([(*target, *online)], tau=0.1)
>>> torch.allclose(target[0] @ target[1], want, atol=1e-5)  # at full rank: exactly the averaged product
True
>>> online = (torch.randn(6, 2, generator=g), torch.randn(2, 5, generator=g))  # rank 2: the best rank-2 fit
>>> target = (torch.randn(6, 2, generator=g), torch.randn(2, 5, generator=g))
>>> want = 0.9 * target[0] @ target[1] + 0.1 * online[0] @ online[1]
>>> product_polyak_([(*target, *online)], tau=0.1)
>>> s = torch.linalg.svdvals(want)
>>> bool(torch.isclose(torch.linalg.matrix_norm(target[0] @ target[1] - want), s[2:].pow(2).sum().sqrt(), atol=1e-5))
True
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.objectives import SoftUpdate

from adarl.core.lowrank import factor_svd, refactorize

__all__ = ["ProductSoftUpdate", "factor_pairs", "product_polyak_"]

#: (target W1, target W2, online W1, online W2) of one factorised layer (any leading batch dimensions)
FactorPair = tuple[Tensor, Tensor, Tensor, Tensor]


def factor_pairs(targets: Mapping[str, Tensor], sources: Mapping[str, Tensor]) -> list[FactorPair]:
    """The factorised layers among flat parameter maps (``"<prefix>.w1"`` beside ``"<prefix>.w2"``, the names of
    :class:`~adarl.core.lowrank.LowRankLinear`), as ``(target w1, target w2, online w1, online w2)``."""
    pairs = []
    for key in targets:
        if not key.endswith("w1"):
            continue
        prefix = key[: -len("w1")]
        if prefix + "w2" in targets and key in sources and prefix + "w2" in sources:
            pairs.append((targets[key], targets[prefix + "w2"], sources[key], sources[prefix + "w2"]))
    return pairs


def factor_keys(pairs_of: Mapping[str, Tensor]) -> set[str]:
    """The keys :func:`factor_pairs` takes from a flat parameter map (both factors of each layer)."""
    keys = set()
    for key in pairs_of:
        if key.endswith("w1") and key[: -len("w1")] + "w2" in pairs_of:
            keys |= {key, key[: -len("w1")] + "w2"}
    return keys


@torch.no_grad()
def averaged_factors(pair: FactorPair, tau: float) -> tuple[Tensor, Tensor]:
    """Balanced rank-``r`` factors of ``(1 - tau) W1' W2' + tau W1 W2`` (``r`` = the target factors' rank)."""
    tw1, tw2, w1, w2 = pair
    r = tw1.shape[-1]
    if w1.shape[-1] != r:
        raise ValueError(f"target and online factors have different ranks ({r} and {w1.shape[-1]})")
    out, inp = tw1.shape[-2], tw2.shape[-1]
    left = torch.cat([(1 - tau) * tw1.double(), tau * w1.double()], dim=-1)  # (..., out, 2r)
    right = torch.cat([tw2.double(), w2.double()], dim=-2)  # (..., 2r, in)
    if 2 * r <= min(out, inp):
        u, s, vh = factor_svd(left, right)  # the QR route: an SVD of a 2r x 2r core
    else:
        product = left @ right
        finite = torch.isfinite(product).flatten(-2).all(-1)
        keep = finite[..., None, None]
        u, s, vh = torch.linalg.svd(torch.where(keep, product, 0.0), full_matrices=False)
        nan = torch.nan
        u, vh = u.masked_fill(~keep, nan), vh.masked_fill(~keep, nan)  # a diverged member stays non-finite
    # a fixed sign per singular pair (the largest entry of each left vector positive): the SVD's signs are
    # arbitrary, and without this two computations of nearly the same product may return factors of opposite sign
    pick = u.abs().argmax(dim=-2, keepdim=True)
    sign = torch.sign(torch.gather(u, -2, pick))
    sign = torch.where(sign == 0, 1.0, sign)
    u, vh = u * sign, vh * sign.mT
    return refactorize(u, s, vh, r, tw1.dtype)


@torch.no_grad()
def product_polyak_(pairs: Sequence[FactorPair], tau: float) -> None:
    """Move each pair's target factors to the balanced rank-``r`` factors of the averaged product, in place."""
    for pair in pairs:
        a, b = averaged_factors(pair, tau)
        pair[0].copy_(a)
        pair[1].copy_(b)


def _flat(td) -> dict[str, Tensor]:
    return dict(td.flatten_keys(".").items()) if isinstance(td, TensorDictBase) else dict(td)


class ProductSoftUpdate(SoftUpdate):
    """TorchRL's :class:`~torchrl.objectives.SoftUpdate` with the factorised layers' targets averaged as products
    (:func:`product_polyak_`); every other tensor is averaged as ``SoftUpdate`` averages it.

    The pairs are looked up on every step from the loss's parameter maps, so rank events (which resize the
    factors) need no notice."""

    def __init__(self, loss_module, *, tau: float) -> None:
        super().__init__(loss_module, tau=tau)
        self.tau = float(tau)

    def _pairs(self) -> list[FactorPair]:
        pairs = []
        for name in self._target_names:
            source_name = name[len("target_") :]
            if not source_name.endswith("_params"):
                continue
            pairs += factor_pairs(_flat(getattr(self.loss_module, name)), _flat(getattr(self.loss_module, source_name)))
        return pairs

    def step(self) -> None:
        pairs = self._pairs()
        new = [averaged_factors(p, self.tau) for p in pairs]  # from the targets before this step
        super().step()
        with torch.no_grad():
            for pair, (a, b) in zip(pairs, new, strict=True):
                pair[0].copy_(a)
                pair[1].copy_(b)
