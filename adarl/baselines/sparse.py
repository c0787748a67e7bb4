"""The sparsification layer of Tiwari et al. (2025), as we interpret it.

Tiwari et al. ("Geometry of neural RL in continuous state and action spaces", arXiv 2507.20853) show that the
states a two-layer policy can reach lie on a manifold of dimension at most ``2 d_a + 1`` (``d_a`` = action
dimension), whatever the observation dimension, and propose replacing one layer of the policy and value networks
with a wide (1024-unit) layer that learns *sparse*, local representations of that manifold. No code was
released and the paper does not pin down the sparsity mechanism, so this module implements one faithful reading,
documented in ``docs/baselines/sparsification.md``:

* a wide linear layer (``width`` units, 1024 by default) followed by the network's activation;
* **k-winners-take-all**: per sample, only the ``k`` largest activations are kept, the rest are set to exactly
  zero. With ``k`` equal to the manifold-dimension bound ``2 d_a + 1`` each input is represented by a small
  local set of units (a local chart of the manifold), and different regions of the state manifold use different
  units. Gradients flow only through the winners.

Why k-WTA rather than an L1 penalty: it guarantees the sparsity level (no coefficient to tune per env), keeps the
loss untouched (so it composes with any TorchRL loss), and ties the one free number, ``k``, to the quantity the
paper derives.
"""

from __future__ import annotations

import torch
from torch import nn

from adarl.baselines.registry import register_network_variant
from adarl.errors import AdaRLValueError

__all__ = ["intrinsic_rank", "KWinnersTakeAll", "SparsificationLayer"]


def intrinsic_rank(action_dim: int) -> int:
    """Tiwari et al.'s bound on the attainable-state manifold dimension, ``2 d_a + 1`` (Hopper: 7, Ant: 17)."""
    if isinstance(action_dim, bool) or not isinstance(action_dim, int) or action_dim < 1:
        raise AdaRLValueError(f"action_dim must be an integer >= 1, got {action_dim!r}")
    return 2 * action_dim + 1


class KWinnersTakeAll(nn.Module):
    """Keep the ``k`` largest entries of the last dimension, zero the others (per sample)."""

    def __init__(self, k: int) -> None:
        super().__init__()
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise AdaRLValueError(f"k must be an integer >= 1, got {k!r}")
        self.k = k

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.k >= x.shape[-1]:
            return x
        # threshold at the k-th largest value (vmap-friendly, no in-place scatter); ties at the threshold are
        # measure-zero for real-valued pre-activations, and ReLU's zeros stay zeros either way
        kth = x.topk(self.k, dim=-1).values[..., -1:]
        return x * (x >= kth)

    def extra_repr(self) -> str:
        return f"k={self.k}"


class SparsificationLayer(nn.Sequential):
    """``Linear(in, width)`` -> activation -> k-winners-take-all: a wide layer with exactly ``k`` active units.

    Its ``nn.Linear`` is a plain hidden layer to everything else (Parseval regularisation and the optimiser see
    it as such); only ``k`` of its ``width`` outputs are non-zero for any input."""

    def __init__(
        self, in_features: int, width: int = 1024, k: int = 32, activation: type[nn.Module] = nn.ReLU, device=None
    ) -> None:
        if isinstance(width, bool) or not isinstance(width, int) or width < 1:
            raise AdaRLValueError(f"width must be an integer >= 1, got {width!r}")
        if isinstance(k, int) and not isinstance(k, bool) and k > width:
            raise AdaRLValueError(f"k must be <= width ({width}), got {k!r}")
        super().__init__(nn.Linear(in_features, width, device=device), activation(), KWinnersTakeAll(k))

    @property
    def width(self) -> int:
        return self[0].out_features

    @property
    def k(self) -> int:
        return self[2].k


def _sparse_variant(mlp_config, algorithm_config, action_dim: int) -> dict:
    """``network.<net>.sparse``: the sparsification layer's arguments (``k`` defaults to the intrinsic rank)."""
    sp = mlp_config.sparse
    if sp.layer is None:
        return {}
    k = sp.k if sp.k is not None else min(intrinsic_rank(action_dim), sp.width)
    return {"sparse_layer": sp.layer, "sparse_width": sp.width, "sparse_k": k}


register_network_variant("sparse", _sparse_variant)
