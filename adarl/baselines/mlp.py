"""One MLP builder for the baselines' network variants: low-rank layers, a sparsification layer, and
Parseval's optional diagonal and input scale layers, in any combination.

The layout is ``[InputScale] -> (hidden layer -> [DiagonalScale] -> activation) x n -> Linear head``; a hidden
layer is an ``nn.Linear``, a :class:`~adarl.core.lowrank.LowRankLinear` (indices in ``low_rank_layers``) or, at index
``sparse_layer``, a :class:`~adarl.baselines.sparse.SparsificationLayer` of ``sparse_width`` units (which brings
its own activation and k-winners-take-all).

It is the registered variant builder (:mod:`adarl.baselines.registry`): the recipe builders call it whenever a
network section asks for a variant.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from adarl.baselines.parseval import DiagonalScale, InputScale
from adarl.baselines.registry import register_variant_builder
from adarl.baselines.sparse import SparsificationLayer
from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLValueError

__all__ = ["BaselineMLP", "make_baseline_mlp"]


class BaselineMLP(nn.Sequential):
    """An ``nn.Sequential`` that, like :class:`torchrl.modules.MLP`, concatenates several inputs (a Q network's
    observation and action) along the last dimension."""

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1)
        return super().forward(x)


def make_baseline_mlp(
    in_features: int,
    out_features: int,
    num_cells: Sequence[int] = (64, 64),
    activation_class: type[nn.Module] = nn.ReLU,
    low_rank_layers: Sequence[int] = (),
    rank: int | None = None,
    sparse_layer: int | None = None,
    sparse_width: int = 1024,
    sparse_k: int = 32,
    diagonal_scale: bool = False,
    input_scale: bool = False,
    device: torch.device | str | None = None,
) -> BaselineMLP:
    """An MLP with the chosen variants (see the module docstring)."""
    n = len(num_cells)
    chosen = set(int(i) for i in low_rank_layers)
    bad = sorted(i for i in chosen if not 0 <= i < n)
    if bad:
        raise AdaRLValueError(f"low_rank_layers {bad} out of range: hidden layers are 0 .. {n - 1}")
    if sparse_layer is not None:
        if not 0 <= sparse_layer < n:
            raise AdaRLValueError(f"sparse_layer must be a hidden-layer index 0 .. {n - 1}, got {sparse_layer!r}")
        if sparse_layer in chosen:
            raise AdaRLValueError(f"layer {sparse_layer} cannot be both low-rank and the sparsification layer")
    layers: list[nn.Module] = [InputScale(device=device)] if input_scale else []
    width_in = int(in_features)
    for i, width in enumerate(num_cells):
        if i == sparse_layer:
            sparse = SparsificationLayer(width_in, sparse_width, sparse_k, activation_class, device=device)
            if diagonal_scale:  # gain between the wide linear layer and its activation
                sparse.insert(1, DiagonalScale(sparse_width, device=device))
            layers.append(sparse)
            width_in = sparse_width
            continue
        if i in chosen:
            layers.append(LowRankLinear(width_in, width, rank=rank, device=device))
        else:
            layers.append(nn.Linear(width_in, width, device=device))
        if diagonal_scale:
            layers.append(DiagonalScale(width, device=device))
        layers.append(activation_class())
        width_in = width
    layers.append(nn.Linear(width_in, out_features, device=device))
    return BaselineMLP(*layers)


register_variant_builder(make_baseline_mlp)
