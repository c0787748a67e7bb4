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

Two computations of the same function and gradients (``SparsificationLayer(form=...)``, :func:`set_form`):

* ``"dense"``: the three modules in turn (``Linear``, activation, ``x * (x >= kth)`` on all ``width`` units). Its
  backward runs the wide layer's two dense matmuls (the weight's and the input's gradient, ``batch x width x in``
  each) and elementwise passes over ``batch x width`` tensors, although only ``k`` units per input carry a
  gradient.
* ``"sparse"`` (the default, for ``Linear -> ReLU -> k-WTA``, the recipes' layer): one
  ``torch.autograd.Function`` (:class:`_SparseReLULinear`). Its forward computes the wide pre-activation (the
  winners must be found among all units), picks the winners with one selection on it (:func:`largest`: ``topk``'s
  values and units, by numpy's ``argpartition`` where PyTorch's CPU ``topk`` is slow; ReLU keeps the order of the
  positive units) and writes their ReLU into that buffer, zeroed: the ``width``-wide output the next layer reads,
  unchanged. Its backward gathers the output's gradient at the winners and reaches ``x``, the weight and the bias
  through the winners' rows alone (``index_select`` / ``index_add_``: ``batch x k x in`` instead of two
  ``batch x width x in`` matmuls). Its outputs are the dense form's values (the same matmul; under ``vmap`` one
  ``baddbmm`` where the dense form adds the bias apart, equal in the tests, in general up to rounding), its
  gradients the dense form's up to summation order, every exact zero included (``tests/test_sparse_fast.py``).

  Ties: the dense form keeps every unit ``>= kth``, so a tie at the ``k``-th value keeps more than ``k`` units.
  :func:`winners` checks for one (the ``k + 1`` largest) and then takes as many units as the widest row keeps, each
  row's surplus masked, so the forms agree on ties too. A unit at exactly 0 after ReLU has output 0 and gradient 0 in
  either form and is not counted (fewer than ``k`` positive units is not a tie). The check reads one boolean per
  forward (a device sync on a GPU).

  Under ``torch.vmap`` (TorchRL's ``SACLoss`` runs its stacked critic ensemble so) the function runs one level
  below the vmap on the stacked tensors (:func:`_under_transform`). Other functorch transforms, another
  activation, a :class:`~adarl.baselines.parseval.DiagonalScale` inside the layer, ``k >= width``, fewer than 32
  input rows (acting one observation at a time), TorchScript, ``torch.compile`` and ``torch.export`` (an exported
  policy) run the dense form.

Speed (``benchmarks/sparse_speed.py``, docs/baselines/sparsification.md): the sparse form saves the backward's wide
matmuls; the forward's (the wide matmul and the selection of the winners, which every form needs) and TorchRL's
per-update overhead remain, so a SAC update of the Hopper recipe gains about a sixth, not a factor. Where PyTorch's
CPU ``topk`` is slow (Ant's and Humanoid's ``k``), :func:`largest` selects with numpy (``benchmarks/sparse_topk.py``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from adarl.baselines.registry import register_network_variant
from adarl.errors import AdaRLValueError

try:  # functorch's interpreter stack, read to step below a vmap level (_under_transform); private, so guarded
    from torch._C._functorch import _add_batch_dim
    from torch._C._functorch import get_unwrapped as _unwrapped
    from torch._C._functorch import is_batchedtensor as _is_batched
    from torch._C._functorch import maybe_get_bdim as _bdim_of
    from torch._C._functorch import maybe_get_level as _level_of
    from torch._functorch.pyfunctorch import TransformType
    from torch._functorch.pyfunctorch import retrieve_current_functorch_interpreter as _current_interpreter

    _VMAP = TransformType.Vmap
except ImportError:  # pragma: no cover - another torch: the dense form under transforms
    _current_interpreter = None

__all__ = [
    "FORMS",
    "intrinsic_rank",
    "KWinnersTakeAll",
    "largest",
    "SparsificationLayer",
    "set_form",
    "sparse_relu_kwta",
    "winners",
]

#: the two computations of :class:`SparsificationLayer` (the same function; the module docstring says how)
FORMS = ("sparse", "dense")

#: below this many input rows the sparse form runs the dense one: one observation at a time (collection,
#: evaluation), its fixed cost of a few dozen small operations outweighs the backward it saves (measured on CPU:
#: about 0.1 ms dense vs 0.25 ms sparse per actor call at 1 row, equal at 100 rows)
_MIN_ROWS = 32


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


def largest(scores: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``scores.topk(m, dim=-1)``: the ``m`` largest values of each row, largest first, and their units, bit for
    bit ``topk``'s (a row with ties among them or NaN is handed to ``topk`` itself, whose order of tied units is its
    implementation's), except where the ``m``-th value recurs outside the ``m``: the ``m``-th unit is then one
    unit of that value, maybe another than ``topk``'s (checking for it costs a pass over the row; :func:`winners`
    asks for ``k + 1`` units and uses the ``m``-th one's value alone).

    Why not always ``topk``: PyTorch's CPU kernel takes a partial heap while ``64 m <= n`` and ``nth_element``
    beyond, which costs more than twice as much; for the layer's ``k + 1`` on Ant (18) and Humanoid (36) of 1024
    units numpy's ``argpartition`` (introselect on the values alone) and a sort of the ``m`` found are 3-4x
    faster on one thread (``benchmarks/sparse_topk.py``). A tensor that needs a gradient, sits off the CPU or is
    not float32/float64, under a functorch transform or ``torch.compile``, and the heap's range keep ``topk``."""
    n = scores.shape[-1]
    if (
        64 * m <= n
        or m >= n
        or scores.device.type != "cpu"
        or scores.dtype not in (torch.float32, torch.float64)
        or scores.requires_grad
        or torch._C._are_functorch_transforms_active()
        or torch.compiler.is_compiling()
    ):
        return scores.topk(m, dim=-1)
    a = scores.numpy()
    found = np.argpartition(a, n - m, axis=-1)[..., n - m :]
    values = np.take_along_axis(a, found, -1)
    order = np.argsort(values, axis=-1)[..., ::-1]
    values = torch.from_numpy(np.take_along_axis(values, order, -1))
    index = torch.from_numpy(np.take_along_axis(found, order, -1).astype(np.int64, copy=False))
    # where topk's order is its implementation's choice (equal values among the m, NaN), those rows are topk's
    # own: it computes each row alone, so their order is topk's bit for bit
    tied = (values[..., 1:] == values[..., :-1]).any(-1) | values.isnan().any(-1)
    if bool(tied.any()):
        values[tied], index[tied] = scores[tied].topk(m, dim=-1)
    return values, index


def winners(
    scores: torch.Tensor, k: int, zeros_dead: bool = False
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The units :class:`KWinnersTakeAll` keeps (``scores >= kth``, ``kth`` the ``k``-th largest score of the row),
    as ``(index, values, keep)`` along the last dimension: ``index`` holds ``k`` units per row (``values`` their
    scores, largest first), or, where some row ties at its ``k``-th score, as many as the widest row keeps, ``keep``
    masking each row's surplus (None where there is none). ``zeros_dead``: a unit scoring 0 or less is inert (ReLU:
    output 0, gradient 0) and not counted, so fewer than ``k`` positive scores is not a tie."""
    vals, idx = largest(scores, k + 1)
    kth, nxt = vals[..., k - 1], vals[..., k]
    tie = nxt == kth
    if zeros_dead:
        tie &= nxt > 0
    if not bool(tie.any()):
        return idx[..., :k], vals[..., :k], None
    kth = kth.unsqueeze(-1)
    kept = scores >= kth
    if zeros_dead:
        kept &= scores > 0
    vals, idx = largest(scores, int(kept.sum(-1).max()))
    keep = vals >= kth
    if zeros_dead:
        keep &= vals > 0
    return idx, vals, keep


def _stacked_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``F.linear`` where ``weight`` may carry leading stacked dimensions ``S`` (``[*S, out, in]``, ``bias``
    ``[*S, out]``) that ``x`` (``[*S, *B, in]``) leads with too: one ``baddbmm`` for the ensemble."""
    if weight.dim() == 2:
        return F.linear(x, weight, bias)
    lead, (out_f, in_f) = weight.shape[:-2], weight.shape[-2:]
    w = weight.reshape(-1, out_f, in_f).transpose(-1, -2)
    x3 = x.reshape(w.shape[0], -1, in_f)
    y = torch.bmm(x3, w) if bias is None else torch.baddbmm(bias.reshape(-1, 1, out_f), x3, w)
    return y.view(*lead, *x.shape[len(lead) : -1], out_f)


class _SparseReLULinear(torch.autograd.Function):
    """``KWinnersTakeAll(k)(relu(F.linear(x, weight, bias)))``, its gradients through the winners alone.

    Shapes: ``weight`` ``[*S, out, in]`` (``S`` empty, or the ensemble dimension(s) :func:`_under_transform`
    stacks), ``bias`` ``[*S, out]`` or None, ``x`` ``[*S, *B, in]``. A ``forward(ctx, ...)`` Function (no
    ``setup_context``): ``apply`` then costs no signature binding per call; under ``vmap`` it is reached through
    :func:`_under_transform`, not functorch's autograd.Function rules."""

    @staticmethod
    def forward(ctx, x, weight, bias, k):
        pre = _stacked_linear(x, weight, bias)
        index, pre_k, keep = winners(pre, k, zeros_dead=True)
        gate = pre_k > 0  # ReLU's gradient mask at the winners
        value = pre_k.clamp_min(0)
        if keep is not None:
            gate &= keep
            value = value * keep
        ctx.save_for_backward(x, weight, index, gate)
        # written into the pre-activation's own buffer: no second batch x width allocation
        return pre.zero_().scatter_(-1, index, value)

    @staticmethod
    def backward(ctx, grad_out):
        x, weight, index, gate = ctx.saved_tensors
        out_f, in_f = weight.shape[-2:]
        lead = weight.shape[:-2]
        s, k = math.prod(lead), index.shape[-1]
        g = (grad_out.gather(-1, index) * gate).reshape(-1, k)  # [s * n, k]
        flat = index.reshape(s, -1)
        if s > 1:  # rows of the [s * out, in] stack of the ensemble's weights
            flat = flat + torch.arange(0, s * out_f, out_f, device=index.device).unsqueeze(-1)
        flat = flat.reshape(-1)
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            rows = weight.reshape(-1, in_f).index_select(0, flat).view(-1, k, in_f)
            grad_x = torch.bmm(g.unsqueeze(1), rows).view(x.shape)
        if ctx.needs_input_grad[1]:
            outer = (g.unsqueeze(-1) * x.reshape(-1, 1, in_f)).view(-1, in_f)
            grad_w = weight.new_zeros(s * out_f, in_f).index_add_(0, flat, outer).view(weight.shape)
        if ctx.needs_input_grad[2]:
            grad_b = weight.new_zeros(s * out_f).index_add_(0, flat, g.reshape(-1)).view(*lead, out_f)
        return grad_x, grad_w, grad_b, None


def _dense_relu_kwta(x, weight, bias, k):
    """The dense form on plain (possibly stacked) tensors: what the three modules compute."""
    h = _stacked_linear(x, weight, bias).relu()
    return h * (h >= h.topk(k, dim=-1).values[..., -1:])


def sparse_relu_kwta(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, k: int) -> torch.Tensor:
    """``KWinnersTakeAll(k)(relu(F.linear(x, weight, bias)))`` on plain tensors, ``weight`` possibly stacked
    (``[*S, out, in]`` with ``x`` ``[*S, *B, in]``: the fused update's critic ensemble): the sparse form (its
    backward through the winners alone), or the dense one for fewer than :data:`_MIN_ROWS` rows and under
    ``torch.compile``, as :class:`SparsificationLayer` chooses; the same values and gradients either way."""
    if torch.compiler.is_compiling() or x.numel() < _MIN_ROWS * x.shape[-1] * math.prod(weight.shape[:-2]):
        return _dense_relu_kwta(x, weight, bias, k)
    return _sparse_relu_linear(x, weight, bias, k)


def _sparse_relu_linear(x, weight, bias, k):
    """:class:`_SparseReLULinear` wherever it is called from: directly, or under functorch transforms."""
    if not torch._C._are_functorch_transforms_active():
        return _SparseReLULinear.apply(x, weight, bias, k)
    return _under_transform(x, weight, bias, k)


def _under_transform(x, weight, bias, k):
    """Under ``torch.vmap`` (TorchRL's critic ensemble): step below the vmap level, as functorch's own rules for
    an autograd.Function do, but without their per-call cost (pytree, signature binding: about as much as the
    sparse backward saves). The vmapped dimension becomes the leading dimension of every tensor (the stacked
    critics' weights, or one more batch dimension of ``x`` where the parameters are shared), the function runs
    there and its output is wrapped back. Another transform (``grad``, ``jvp``, ...), or a torch without these
    functorch internals, gets the dense form, which every transform handles."""
    interpreter = _current_interpreter() if _current_interpreter is not None else None
    if interpreter is None or interpreter.key() != _VMAP:
        return _dense_relu_kwta(x, weight, bias, k)
    level, n = interpreter.level(), interpreter.batch_size()

    def unwrap(t):
        if t is not None and _is_batched(t) and _level_of(t) == level:
            return _unwrapped(t), _bdim_of(t)
        return t, None

    (x, dx), (weight, dw), (bias, db) = unwrap(x), unwrap(weight), unwrap(bias)

    def front(t, dim):
        return t.movedim(dim, 0) if dim is not None else t.expand(n, *t.shape)

    with interpreter.lower():
        if dx is None and dw is None and db is None:  # nothing batched at this level
            return _sparse_relu_linear(x, weight, bias, k)
        if dw is None and db is None and weight.dim() == 2:  # shared parameters: one more batch dimension of x
            out = _sparse_relu_linear(front(x, dx), weight, bias, k)
        else:  # stacked parameters (the critic ensemble): one more leading (stacked) dimension on each
            b = None if bias is None else front(bias, db)
            out = _sparse_relu_linear(front(x, dx), front(weight, dw), b, k)
    return _add_batch_dim(out, 0, level)


class SparsificationLayer(nn.Sequential):
    """``Linear(in, width)`` -> activation -> k-winners-take-all: a wide layer with exactly ``k`` active units.

    Its ``nn.Linear`` is a plain hidden layer to everything else (Parseval regularisation and the optimiser see
    it as such); only ``k`` of its ``width`` outputs are non-zero for any input. ``form`` (:data:`FORMS`) picks
    the computation, ``"sparse"`` (the default) or ``"dense"``: the same function and gradients (the module
    docstring says where each runs); :func:`set_form` switches the layers of a built network."""

    def __init__(
        self,
        in_features: int,
        width: int = 1024,
        k: int = 32,
        activation: type[nn.Module] = nn.ReLU,
        device=None,
        form: str = "sparse",
    ) -> None:
        if isinstance(width, bool) or not isinstance(width, int) or width < 1:
            raise AdaRLValueError(f"width must be an integer >= 1, got {width!r}")
        if isinstance(k, int) and not isinstance(k, bool) and k > width:
            raise AdaRLValueError(f"k must be <= width ({width}), got {k!r}")
        if form not in FORMS:
            raise AdaRLValueError(f"form must be one of {FORMS}, got {form!r}")
        super().__init__(nn.Linear(in_features, width, device=device), activation(), KWinnersTakeAll(k))
        self.form = form

    @property
    def width(self) -> int:
        return self[0].out_features

    @property
    def k(self) -> int:
        return self[-1].k

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.jit.is_scripting():  # an exported policy: plain modules
            for module in self:
                x = module(x)
            return x
        if (
            self.form == "dense"
            or torch.compiler.is_compiling()  # first: a batch-size test would specialise an export's batch dimension
            or x.numel() < _MIN_ROWS * x.shape[-1]  # acting in the environment: bookkeeping outweighs the saving
            or not self._sparse_form_applies()
        ):
            for module in self:
                x = module(x)
            return x
        return _sparse_relu_linear(x, self[0].weight, self[0].bias, self[-1].k)

    @torch.jit.unused
    def fused_kernel(self):
        """How the fused SAC update computes this layer (:func:`adarl.fast.sac.fused_kernel`): ``(kernel, weight name,
        bias name)`` with ``kernel(x, weight, bias)`` = :func:`sparse_relu_kwta` at this ``k``, for the layout
        ``Linear -> ReLU -> KWinnersTakeAll`` with ``k`` below the width; None for any other."""
        if not self._sparse_form_applies():
            return None
        return functools.partial(sparse_relu_kwta, k=self.k), "0.weight", "0.bias" if self[0].bias is not None else None

    @torch.jit.unused
    def _sparse_form_applies(self) -> bool:
        """The layout the sparse form computes: ``Linear -> ReLU -> KWinnersTakeAll`` with ``k < width``."""
        return (
            len(self) == 3
            and type(self[0]) is nn.Linear
            and type(self[1]) is nn.ReLU
            and isinstance(self[2], KWinnersTakeAll)
            and self[2].k < self[0].out_features
        )

    def extra_repr(self) -> str:
        return f"form={self.form!r}"


def set_form(modules: nn.Module | Iterable[nn.Module], form: str) -> int:
    """Set ``form`` (:data:`FORMS`) on every :class:`SparsificationLayer` inside ``modules`` (a module or several,
    e.g. ``(loss.actor_network, loss.qvalue_network)``: a ``SACLoss`` does not list its networks in
    ``loss.modules()``); returns how many layers it set."""
    if form not in FORMS:
        raise AdaRLValueError(f"form must be one of {FORMS}, got {form!r}")
    roots = [modules] if isinstance(modules, nn.Module) else list(modules)
    layers = {id(m): m for root in roots for m in root.modules() if isinstance(m, SparsificationLayer)}
    for layer in layers.values():
        layer.form = form
    return len(layers)


def _sparse_variant(mlp_config, algorithm_config, action_dim: int) -> dict:
    """``network.<net>.sparse``: the sparsification layer's arguments (``k`` defaults to the intrinsic rank)."""
    sp = mlp_config.sparse
    if sp.layer is None:
        return {}
    k = sp.k if sp.k is not None else min(intrinsic_rank(action_dim), sp.width)
    return {"sparse_layer": sp.layer, "sparse_width": sp.width, "sparse_k": k}


register_network_variant("sparse", _sparse_variant)
