"""Small kernels the fused SAC step and its hand-written backward share: an affine map in one ATen call, and
``torch.compile`` from a fresh code object (one compilation per rank event).

Used by :mod:`adarl.fast.sac` and :mod:`adarl.fast.manual_backward`.

Mirrors: ``torch.nn.Linear``'s ``x @ weight.T + bias`` (and the stacked critics' ``bmm``), and ``torch.compile`` of
the same method.
Equality: through the fused step, against TorchRL's ``SACLoss``
(``tests/test_fast_sac.py::test_losses_and_gradients_match_sacloss``) and compiled against eager
(``tests/test_fast_sac.py::test_compiled_update_recompiles_once_per_rank_event``).
"""

from __future__ import annotations

import types

import torch

__all__ = ["affine", "compile_fresh"]


def affine(x: torch.Tensor, w_t: torch.Tensor, b: torch.Tensor | None) -> torch.Tensor:
    """``x @ w_t + b`` with the bias added inside the matmul kernel (``addmm``/``baddbmm``): one operation, and
    one autograd node, instead of three (matmul, unsqueeze, add); at (64, 64) the update is op-count bound.

    ``w_t`` is ``[in, out]`` (actor) or ``[N, in, out]`` (stacked critics, ``x`` then ``[B, in]`` or ``[N, B, in]``).
    """
    if b is None:
        return torch.matmul(x, w_t)
    if w_t.dim() == 2 and x.dim() == 2:
        return torch.addmm(b, x, w_t)
    if w_t.dim() == 3 and x.dim() in (2, 3):
        if x.dim() == 2:
            x = x.expand(w_t.shape[0], *x.shape)
        return torch.baddbmm(b.unsqueeze(-2), x, w_t)
    return torch.matmul(x, w_t) + b.unsqueeze(-2)


def compile_fresh(function, owner, name: str, backend):
    """``torch.compile`` of ``function`` bound to ``owner`` (None: unbound), from a fresh copy of its code object.

    Why: a fresh code object has a fresh dynamo cache, so rebuilding at each rank event compiles exactly once per
    event and dynamo's recompile limit (8 by default) is never reached: no silent fall-back to eager. ``backend``
    is ``torch.compile``'s (a name, or a callable backend)."""
    fresh = types.FunctionType(function.__code__.replace(), function.__globals__, name)
    target = fresh if owner is None else types.MethodType(fresh, owner)
    return torch.compile(target, backend=backend, fullgraph=True, dynamic=False)
