"""Low-rank linear layers: ``W = W1 @ W2`` with a bias-free bottleneck (paper Fig. 5, App. D.2).

The factorised layer is what makes a rank constraint cheap: between rank events the optimiser trains the two
factors, and the product can never exceed rank ``r``. A rank event SVDs the product and re-factorises it as
``W1 = U sqrt(S)``, ``W2 = sqrt(S) V^T`` (the balanced split, so neither factor dominates the gradients).

The SVD helpers here work on batched factors (leading dimensions are kept) so that the same code serves a
single module and the stacked Q-ensemble parameters that :class:`~torchrl.objectives.SACLoss` trains under
vmap.
"""

from __future__ import annotations

import math
import numbers
import weakref
from collections.abc import Callable, Iterable, Iterator, Sequence

import torch
from torch import nn
from torch.nn import functional as F
from torchrl.modules import MLP

from adarl.errors import AdaRLValueError

__all__ = [
    "LowRankLinear",
    "factor_svd",
    "refactorize",
    "truncation_error",
    "low_rank_mlp",
    "iter_low_rank",
    "is_integer",
]


def is_integer(value) -> bool:
    """Whether ``value`` is an integer (``int``, ``numpy.int64``, ...), not a ``bool`` or a float such as ``8.7``."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def replace_data(t: torch.Tensor, value: torch.Tensor) -> None:
    """``t.data = value`` keeping ``t``'s identity, dtype and device; clears ``.grad``.

    A leaf's cached gradient accumulator (kept alive by any autograd graph still referenced, e.g. last step's loss
    tensor) records the leaf's old shape, and ``set_data`` only drops it on a dtype/device change: the next
    backward would then fail with "invalid gradient ... expected shape". Passing through another dtype first
    makes autograd drop the stale accumulator, so a graph left alive across a shape change is harmless.
    """
    value = value.to(device=t.device, dtype=t.dtype).contiguous()
    if t.requires_grad:
        other = torch.float64 if t.dtype != torch.float64 else torch.float32
        t.data = value.to(other)
    t.data = value
    if getattr(t, "grad", None) is not None:
        t.grad = None


# Above this fraction of min(out, in) the QR + core route costs more than a decomposition of the product itself
# (measured on CPU, one thread: the crossover is at 0.7-0.8; at full rank the QR route is ~1.6x slower).
_DIRECT_SVD_FRACTION = 0.75

# The product route diagonalises the Gram matrix, whose eigenvalues are the squared singular values: float64
# then resolves s_i to an absolute error of ~1e-16 s_1^2 / s_i. While the r values kept satisfy
# s_r >= _GRAM_MIN_RATIO * s_1 that is <= ~1e-10 s_1, far below the ~6e-8 s_1 by which rounding the float32
# parameters already moves every singular value; a more ill-conditioned product (a collapsed or zero-padded
# layer) takes the SVD of the product instead.
_GRAM_MIN_RATIO = 1e-6


def _gram_svd(m: torch.Tensor, r: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Top-``r`` singular triplets of float64 ``m`` from ``eigh`` of its smaller Gram matrix, or ``None``.

    Why: at full rank a symmetric eigendecomposition is ~2x cheaper than ``torch.linalg.svd`` (divide and
    conquer in both cases), which is most of a rank event on wide layers. The right (or left) singular vectors
    come from ``eigh``; the other side is ``m v / s`` with ``s = ||m v||``, so ``U diag(s) Vh`` is exactly the
    projection ``m V V^T`` onto the kept singular subspace, whatever the rounding in ``V``.
    """
    wide = m.shape[-1] > m.shape[-2]
    a = m.mT if wide else m  # (..., long, short): diagonalise the short side's Gram matrix
    _, v = torch.linalg.eigh(a.mT @ a)  # ascending
    v = v.flip(-1)[..., :r]
    b = a @ v
    s = torch.linalg.vector_norm(b, dim=-2)
    order = s.argsort(dim=-1, descending=True)
    s = s.gather(-1, order)
    # s_1 > 0 too: a zero product passes the ratio test (0 >= 0) and would divide 0 by 0 below.
    if (
        not bool((s[..., 0] > 0).all())
        or not bool((s[..., -1] >= _GRAM_MIN_RATIO * s[..., 0]).all())
        or not bool(torch.isfinite(s).all())
    ):
        return None
    b = b.gather(-1, order.unsqueeze(-2).expand_as(b))
    v = v.gather(-1, order.unsqueeze(-2).expand_as(v))
    u = b / s.unsqueeze(-2)
    return (v, s, u.mT) if wide else (u, s, v.mT)


def factor_svd(w1: torch.Tensor, w2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact thin SVD of ``w1 @ w2`` without forming a full-size SVD.

    ``w1`` is ``(..., out, r)`` and ``w2`` is ``(..., r, in)`` with ``r <= min(out, in)``. QR of ``w1`` and of
    ``w2^T`` reduces the problem to the SVD of an ``r x r`` core; everything runs in float64 (at energy
    thresholds near 1, float32 shares are not reliable). When ``r`` is close to ``min(out, in)`` (above
    ``0.75 min(out, in)``) the QR steps cost more than they save, and the float64 product is decomposed
    directly: by ``eigh`` of its Gram matrix while the kept spectrum is well conditioned (``s_r >= 1e-6 s_1``,
    about twice as fast as an SVD), else by ``torch.linalg.svd`` (same result to rounding). Returns
    ``U (..., out, r)``, ``S (..., r)`` (descending) and ``Vh (..., r, in)``, all float64. A member whose factors
    hold NaN or inf gets all-NaN outputs (the decompositions would raise on it), so rank rules see a non-finite
    spectrum and skip it, as they promise; the other members are decomposed as usual.
    """
    a = w1.detach().to(torch.float64)
    b = w2.detach().to(torch.float64)
    finite = torch.isfinite(a).flatten(-2).all(-1) & torch.isfinite(b).flatten(-2).all(-1)
    if not bool(finite.all()):
        keep = finite[..., None, None]
        u, s, vh = factor_svd(torch.where(keep, a, 0.0), torch.where(keep, b, 0.0))
        nan = math.nan
        return u.masked_fill(~keep, nan), s.masked_fill(~finite[..., None], nan), vh.masked_fill(~keep, nan)
    r = a.shape[-1]
    if r > _DIRECT_SVD_FRACTION * min(a.shape[-2], b.shape[-1]):
        product = a @ b
        fast = _gram_svd(product, r)
        if fast is not None:
            return fast
        u, s, vh = torch.linalg.svd(product, full_matrices=False)
        return u[..., :, :r], s[..., :r], vh[..., :r, :]
    q1, r1 = torch.linalg.qr(a, mode="reduced")
    q2, r2 = torch.linalg.qr(b.transpose(-1, -2), mode="reduced")
    core = r1 @ r2.transpose(-1, -2)
    uc, s, vhc = torch.linalg.svd(core, full_matrices=False)
    return q1 @ uc, s, vhc @ q2.transpose(-1, -2)


def refactorize(
    u: torch.Tensor, s: torch.Tensor, vh: torch.Tensor, rank: int, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Balanced factors of the best rank-``rank`` approximation: ``W1 = U sqrt(S)``, ``W2 = sqrt(S) V^T``."""
    root = s[..., :rank].sqrt()
    w1 = u[..., :, :rank] * root.unsqueeze(-2)
    w2 = root.unsqueeze(-1) * vh[..., :rank, :]
    return w1.to(dtype).contiguous(), w2.to(dtype).contiguous()


def truncation_error(s: torch.Tensor, rank: int) -> torch.Tensor:
    """``||W - Pi_rank(W)||_F`` from the singular values (Eckart-Young-Mirsky)."""
    return s[..., rank:].pow(2).sum(-1).sqrt()


# In-place methods that do not write the tensor's values (nothing to store in the factors).
_NOT_WRITES = frozenset({"requires_grad_", "share_memory_", "retain_grad", "register_hook", "record_stream"})
_INPLACE_DUNDERS = frozenset(
    {
        "__setitem__",
        "__iadd__",
        "__isub__",
        "__imul__",
        "__itruediv__",
        "__ifloordiv__",
        "__imod__",
        "__ipow__",
        "__imatmul__",
        "__iand__",
        "__ior__",
        "__ixor__",
        "__ilshift__",
        "__irshift__",
    }
)


def _shares_storage(a: torch.Tensor, b: torch.Tensor) -> bool:
    try:
        return a.untyped_storage().data_ptr() == b.untyped_storage().data_ptr() and a.device == b.device
    except (RuntimeError, NotImplementedError):  # tensors without storage (meta, functorch wrappers)
        return False


class _ProductWeight(torch.Tensor):
    """:attr:`LowRankLinear.weight`: the product ``W1 @ W2``, and in-place writes into it reach the layer.

    Why: the weight is computed on access, so without this ``nn.init.orthogonal_(layer.weight)`` would write into a
    temporary and silently change nothing. Every in-place operation on this tensor, or on a view of it (views and
    ``.data``/``.detach()`` keep this type), runs as usual and then stores the whole written product in the layer
    (:meth:`LowRankLinear.set_weight_`). Results that do not alias it are plain tensors.
    """

    @staticmethod
    def wrap(t: torch.Tensor, layer: LowRankLinear, root: torch.Tensor | None = None) -> _ProductWeight:
        out = t.as_subclass(_ProductWeight)
        out._layer_ref = weakref.ref(layer)
        out._root = t if root is None else root
        return out

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        inplace = name in _INPLACE_DUNDERS or (
            name.endswith("_") and not name.endswith("__") and name not in _NOT_WRITES
        )
        written = []
        if inplace and args and isinstance(args[0], cls):
            written.append(args[0])
        outs = kwargs.get("out")
        for t in outs if isinstance(outs, (tuple, list)) else (outs,):
            if isinstance(t, cls):
                written.append(t)
        with torch._C.DisableTorchFunctionSubclass():
            result = func(*args, **kwargs)
        for t in written:
            layer = t._layer_ref()
            if layer is not None:
                layer.set_weight_(t._root)
        if written:
            return result
        src = next((a for a in args if isinstance(a, cls)), None)
        if (
            src is not None
            and isinstance(result, torch.Tensor)
            and not isinstance(result, cls)
            and _shares_storage(result, src)
        ):
            layer = src._layer_ref()
            if layer is not None:
                return cls.wrap(result, layer, src._root)
        return result

    def _as_tensor(self) -> torch.Tensor:
        with torch._C.DisableTorchFunctionSubclass():
            return torch.Tensor.as_subclass(self, torch.Tensor)

    def __repr__(self, **kwargs) -> str:
        return repr(self._as_tensor())

    def __deepcopy__(self, memo) -> torch.Tensor:  # a copy is a plain tensor: it is no longer the layer's weight
        with torch._C.DisableTorchFunctionSubclass():
            return self._as_tensor().detach().clone()

    def __reduce_ex__(self, protocol):  # saved (torch.save, pickle) as a plain tensor
        with torch._C.DisableTorchFunctionSubclass():
            return self._as_tensor().detach().__reduce_ex__(protocol)


class LowRankLinear(nn.Module):
    """A linear layer ``y = x W2^T W1^T + b`` whose weight ``W = W1 W2`` has rank at most ``rank``.

    ``w1`` is ``(out_features, rank)``, ``w2`` is ``(rank, in_features)``; the bottleneck has no bias or
    activation, so the layer is exactly a linear map of rank ``<= rank``. ``rank=None`` means full rank
    ``min(in_features, out_features)``, which represents every dense layer. Initialisation draws a dense
    weight the way :class:`torch.nn.Linear` does and factorises it, so a full-rank layer starts out as a
    standard ``nn.Linear`` would.

    The layer is a plain module with plain parameters, so it works as the ``layer_class`` of
    :class:`torchrl.modules.MLP`, inside ``TensorDictModule``/``ProbabilisticActor``/``ValueOperator`` and
    under ``torch.vmap`` with stacked parameters (the Q ensemble of ``SACLoss``).

    >>> layer = LowRankLinear(11, 64, rank=8)
    >>> layer.w1.shape, layer.w2.shape, layer.rank
    (torch.Size([64, 8]), torch.Size([8, 11]), 8)
    >>> layer(torch.randn(5, 11)).shape
    torch.Size([5, 64])
    >>> int(torch.linalg.matrix_rank(layer.weight))
    8
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        rank: int | None = None,
        bias: bool = True,
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if not (is_integer(in_features) and is_integer(out_features)) or in_features < 1 or out_features < 1:
            raise AdaRLValueError(
                f"LowRankLinear needs integer in_features >= 1 and out_features >= 1, got ({in_features!r}, "
                f"{out_features!r})"
            )
        self.in_features = int(in_features)
        self.out_features = int(out_features)
        rank = self._check_rank(rank)
        factory = {"device": device, "dtype": dtype}
        self.w1 = nn.Parameter(torch.empty(self.out_features, rank, **factory))
        self.w2 = nn.Parameter(torch.empty(rank, self.in_features, **factory))
        if bias:
            self.bias = nn.Parameter(torch.empty(self.out_features, **factory))
        else:
            self.register_parameter("bias", None)
        self.reset_parameters()

    @property
    def max_rank(self) -> int:
        """The largest rank a ``(out, in)`` matrix can have: ``min(in_features, out_features)``."""
        return min(self.in_features, self.out_features)

    @property
    def rank(self) -> int:
        """The current bottleneck width (an upper bound on the rank of :attr:`weight`)."""
        return self.w2.shape[-2]

    @property
    def weight(self) -> torch.Tensor:
        """The dense product ``W1 @ W2`` (``(out_features, in_features)``), computed on access.

        Writes into it go through: an in-place operation on the returned tensor or on a view of it
        (``nn.init.orthogonal_(layer.weight)``, ``layer.weight.mul_(2)``, ``layer.weight[0] = ...``) stores the
        written weight's best rank-``rank`` factorisation in ``w1``/``w2`` (:meth:`set_weight_`; exact at full rank).
        Without this an init loop over ``.weight`` would write into a temporary and change nothing.
        """
        return _ProductWeight.wrap(self.w1 @ self.w2, self)

    def _check_rank(self, rank: int | None) -> int:
        if rank is None:
            return self.max_rank
        if not is_integer(rank) or not 1 <= rank <= self.max_rank:
            raise AdaRLValueError(
                f"rank must be an integer in [1, {self.max_rank}] (min(in_features={self.in_features}, "
                f"out_features={self.out_features})) or None for full rank, got {rank!r}"
            )
        return int(rank)

    @torch.no_grad()
    def set_weight_(self, weight: torch.Tensor) -> LowRankLinear:
        """Store the best rank-``rank`` approximation of a dense ``(out_features, in_features)`` weight, balanced.

        The rank is kept (exact when the weight's rank is at most ``rank``, e.g. at full rank); ``w1``/``w2`` are
        written in place (``copy_``), so optimisers and modules holding them keep working.
        """
        weight = torch.as_tensor(weight).detach()
        shape = (self.out_features, self.in_features)
        lead = tuple(self.w1.shape[:-2])  # a stacked ensemble's members (TorchRL's vmapped Q networks)
        if tuple(weight.shape) not in (shape, lead + shape):
            raise AdaRLValueError(
                f"set_weight_: the weight must have shape (out_features, in_features) = {shape}"
                + (f" or one per ensemble member, {lead + shape}" if lead else "")
                + f", got {tuple(weight.shape)}"
            )
        if not bool(torch.isfinite(weight).all()):
            raise AdaRLValueError("set_weight_: the weight holds NaN or inf values")
        dense = weight.to(device=self.w1.device, dtype=torch.float64)
        u, s, vh = torch.linalg.svd(dense, full_matrices=False)
        w1, w2 = refactorize(u, s, vh, self.rank, self.w1.dtype)
        self.w1.copy_(w1)
        self.w2.copy_(w2)
        return self

    @torch.no_grad()
    def init_weight_(self, init: Callable[..., object], *args, **kwargs) -> LowRankLinear:
        """Initialise the weight with an ``nn.init`` function and keep its best rank-``rank`` factorisation.

        ``init(dense, *args, **kwargs)`` fills a dense float64 ``(out_features, in_features)`` tensor in place
        (e.g. ``layer.init_weight_(nn.init.orthogonal_, gain=math.sqrt(2))``, the baselines' orthogonal init).
        Initialising the factors themselves would not give the product the init's distribution. With stacked
        factors (a TorchRL loss's Q ensemble, whose parameters ``TensorDictParams.to_module`` swaps in, e.g. under
        ``loss.reset_parameters_recursive()``) every member gets a draw of its own: one draw copied into all of
        them would make the twin critics identical for the rest of training.
        """
        if not callable(init):
            raise AdaRLValueError(f"init_weight_: init must be a callable such as nn.init.orthogonal_, got {init!r}")
        lead = tuple(self.w1.shape[:-2])
        dense = torch.empty(*lead, self.out_features, self.in_features, dtype=torch.float64, device=self.w1.device)
        for member in dense.view(-1, self.out_features, self.in_features):  # each 2-D slice: the init's own fans
            init(member, *args, **kwargs)
        return self.set_weight_(dense)

    @torch.no_grad()
    def reset_parameters(self) -> None:
        """Draw a dense weight as ``nn.Linear`` does and store its best rank-``rank`` factorisation."""
        self.init_weight_(nn.init.kaiming_uniform_, a=math.sqrt(5))
        if self.bias is not None:
            bound = 1.0 / math.sqrt(self.in_features)
            nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(F.linear(x, self.w2), self.w1, self.bias)

    def singular_values(self) -> torch.Tensor:
        """Singular values of :attr:`weight` (``rank`` of them, descending, float64), via :func:`factor_svd`."""
        return factor_svd(self.w1, self.w2)[1]

    @torch.no_grad()
    def truncate_(
        self, rank: int, optimizers: torch.optim.Optimizer | Iterable[torch.optim.Optimizer] = ()
    ) -> LowRankLinear:
        """Project the weight onto rank ``rank`` in place and re-factorise it balanced.

        The parameters keep their identity (``.data`` is replaced), so modules, collectors and loss modules
        that hold them see the new tensors; ``.grad`` is cleared, and a graph still alive from the last step
        (a loss tensor you kept) does not break the next ``backward()``. The optimiser state of ``w1``/``w2``
        (Adam moments of the old shape and basis) is dropped in each of ``optimizers``; pass every optimiser
        that trains them (:class:`adarl.RankAdapter` does all of this for a loss). ``rank`` may not exceed the
        current rank; factors holding NaN or inf are refused.
        """
        if not is_integer(rank) or not 1 <= rank <= self.rank:
            raise AdaRLValueError(
                f"truncate_ rank must be an integer in [1, {self.rank}] (the current rank), got {rank!r}"
            )
        bad = [n for n, t in (("w1", self.w1), ("w2", self.w2)) if not bool(torch.isfinite(t).all())]
        if bad:
            raise AdaRLValueError(
                f"truncate_: {' and '.join(bad)} hold NaN or inf (training diverged?); nothing to "
                f"project. Re-initialise the layer (reset_parameters) or restore a checkpoint"
            )
        if isinstance(optimizers, torch.optim.Optimizer):
            optimizers = [optimizers]
        optimizers = list(optimizers)
        u, s, vh = factor_svd(self.w1, self.w2)
        w1, w2 = refactorize(u, s, vh, int(rank), self.w1.dtype)
        replace_data(self.w1, w1)
        replace_data(self.w2, w2)
        for opt in optimizers:
            opt.state.pop(self.w1, None)
            opt.state.pop(self.w2, None)
        return self

    @classmethod
    def from_linear(cls, linear: nn.Linear, rank: int | None = None) -> LowRankLinear:
        """A :class:`LowRankLinear` holding the best rank-``rank`` approximation of ``linear`` (exact at full rank)."""
        layer = cls(
            linear.in_features,
            linear.out_features,
            rank=rank,
            bias=linear.bias is not None,
            device=linear.weight.device,
            dtype=linear.weight.dtype,
        )
        with torch.no_grad():
            u, s, vh = torch.linalg.svd(linear.weight.detach().to(torch.float64), full_matrices=False)
            w1, w2 = refactorize(u, s, vh, layer.rank, layer.w1.dtype)
            layer.w1.copy_(w1)
            layer.w2.copy_(w2)
            if linear.bias is not None:
                layer.bias.copy_(linear.bias)
        return layer

    def extra_repr(self) -> str:
        return (
            f"in_features={self.in_features}, out_features={self.out_features}, rank={self.rank}, "
            f"max_rank={self.max_rank}, bias={self.bias is not None}"
        )


def iter_low_rank(module: nn.Module, prefix: str = "") -> Iterator[tuple[str, LowRankLinear]]:
    """Yield ``(qualified_name, layer)`` for every :class:`LowRankLinear` inside ``module``."""
    for name, sub in module.named_modules(prefix=prefix):
        if isinstance(sub, LowRankLinear):
            yield name, sub


def _layer_factory(
    in_features: int, out_features: int, bias: bool = True, rank: int | None | str = "dense", device=None, dtype=None
) -> nn.Module:
    if rank == "dense":
        return nn.Linear(in_features, out_features, bias=bias, device=device, dtype=dtype)
    return LowRankLinear(in_features, out_features, rank=rank, bias=bias, device=device, dtype=dtype)


def low_rank_mlp(
    in_features: int,
    out_features: int | Sequence[int],
    num_cells: Sequence[int] = (64, 64),
    activation_class: type[nn.Module] | Callable[[], nn.Module] = nn.ReLU,
    low_rank_layers: Sequence[int] = (0, 1),
    rank: int | None | Sequence[int | None] = None,
    device: torch.device | str | None = None,
) -> nn.Module:
    """A :class:`torchrl.modules.MLP` whose chosen hidden layers are :class:`LowRankLinear`.

    ``low_rank_layers`` indexes the ``len(num_cells) + 1`` linear layers (default: the first two, as in the
    paper); the output head may not be low-rank (it stays a plain ``nn.Linear``). ``rank`` is the initial
    rank, one value for all chosen layers or one per chosen layer (``None`` = full rank).

    >>> net = low_rank_mlp(11, 6, num_cells=(64, 64), rank=[11, 32])
    >>> [type(m).__name__ for m in list(net)[::2]], net[0].rank, net[2].rank
    (['LowRankLinear', 'LowRankLinear', 'Linear'], 11, 32)
    >>> net(torch.randn(4, 11)).shape
    torch.Size([4, 6])
    """
    n_layers = len(num_cells) + 1
    chosen = sorted(set(int(i) for i in low_rank_layers))
    bad = [i for i in chosen if not 0 <= i < n_layers - 1]
    if bad:
        raise AdaRLValueError(
            f"low_rank_layers {bad} out of range: with num_cells={list(num_cells)} the hidden layers are "
            f"{list(range(n_layers - 1))} (the output head, index {n_layers - 1}, stays a plain Linear)"
        )
    if rank is None or is_integer(rank):
        ranks = [rank] * len(chosen)
    else:
        ranks = list(rank)
        if len(ranks) != len(chosen):
            raise AdaRLValueError(
                f"rank has {len(ranks)} entries but low_rank_layers has {len(chosen)}: give one rank per layer"
            )
    per_layer = {i: r for i, r in zip(chosen, ranks)}
    widths_in = [int(in_features), *num_cells]
    widths_out = list(num_cells)
    for i, r in per_layer.items():
        limit = min(widths_in[i], widths_out[i])
        if r is not None and (not is_integer(r) or not 1 <= r <= limit):
            raise AdaRLValueError(f"rank for layer {i} must be an integer in [1, {limit}] or None, got {r!r}")
    layer_kwargs = [{"rank": per_layer.get(i, "dense")} for i in range(n_layers)]
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(num_cells),
        activation_class=activation_class,
        layer_class=_layer_factory,
        layer_kwargs=layer_kwargs,
        device=device,
    )
