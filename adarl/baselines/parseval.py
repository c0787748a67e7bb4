"""Parseval regularisation (Chung et al., 2024) as a term added to any TorchRL loss.

``lam * sum_W (base_width / width_W)^2 * ||W W^T - s I||_F^2`` over the *hidden* linear layers of every network a
loss holds (the input layer included; output layers and biases excluded), which keeps the rows of each weight
matrix close to orthogonal with squared norm ``s`` and so preserves plasticity under changing dynamics.

Why a separate term rather than a wrapper loss: TorchRL losses keep their networks functionally (SACLoss stacks
the critic ensemble into new ``[n, out, in]`` parameters), so the term must read the weights the loss trains,
not the modules it was given. :func:`parseval_weights` finds them for any loss that follows TorchRL's
``<name>_network`` / ``<name>_network_params`` convention (or holds plain modules), and
:class:`ParsevalRegularizer` adds ``loss_parseval`` to the loss's output when used through :meth:`wrap_output`.
:class:`~adarl.core.lowrank.LowRankLinear` layers count with their product ``W = W1 @ W2``.

The optional layers of the paper, :class:`DiagonalScale` (a learnable per-unit gain after each hidden linear
layer) and :class:`InputScale` (one learnable scalar on the input), are built into the networks by
:func:`adarl.baselines.mlp.make_baseline_mlp`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn

from adarl.baselines.registry import register_loss_term, register_network_variant
from adarl.core.adapter import network_candidates
from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLValueError

__all__ = [
    "ParsevalWeight",
    "parseval_weights",
    "parseval_penalty",
    "ParsevalRegularizer",
    "DiagonalScale",
    "InputScale",
]


@dataclass
class ParsevalWeight:
    """One hidden layer's weight as the loss trains it: a full matrix or the two low-rank factors.

    Tensors may carry leading ensemble dimensions (``[n, out, in]`` for SACLoss's stacked critics)."""

    path: str
    weight: torch.Tensor | None = None
    w1: torch.Tensor | None = None
    w2: torch.Tensor | None = None

    @property
    def width(self) -> int:
        """Output width of the layer (rows of ``W``), the ``width`` of the ``(64 / width)^2`` scaling."""
        return int((self.weight if self.weight is not None else self.w1).shape[-2])

    def gram(self) -> torch.Tensor:
        """``W W^T`` (``w1 (w2 w2^T) w1^T`` for a low-rank layer, without forming ``W``)."""
        if self.weight is not None:
            return self.weight @ self.weight.transpose(-1, -2)
        inner = self.w2 @ self.w2.transpose(-1, -2)
        return self.w1 @ inner @ self.w1.transpose(-1, -2)


def parseval_penalty(gram: torch.Tensor, s: float = 2.0) -> torch.Tensor:
    """``||G - s I||_F^2`` summed over any leading (ensemble) dimensions of ``G = W W^T``."""
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    return (gram - s * eye).pow(2).sum()


def _linear_layers(network: nn.Module) -> list[tuple[str, nn.Module]]:
    return [(p, m) for p, m in network.named_modules() if isinstance(m, (nn.Linear, LowRankLinear))]


def parseval_weights(loss: nn.Module, networks: Iterable[str] | None = None) -> list[ParsevalWeight]:
    """The hidden-layer weights of every network of ``loss`` (or of the named ones), as the loss trains them.

    The last linear layer of each network is its output layer and is left out. ``loss`` may also be a plain
    ``nn.Module`` (a single network)."""
    candidates = network_candidates(loss) if not isinstance(loss, (nn.Sequential,)) else []
    if not candidates or not any(_linear_layers(m) for _, m in candidates):
        candidates = [("network", loss)]
    if networks is not None:
        wanted = set(networks)
        names = [n for n, _ in candidates]
        missing = wanted - set(names)
        if missing:
            raise AdaRLValueError(f"networks {sorted(missing)} not found in the loss; it has: {names}")
        candidates = [(n, m) for n, m in candidates if n in wanted]
    found: list[ParsevalWeight] = []
    seen: set[int] = set()
    for name, network in candidates:
        params = getattr(loss, f"{name}_params", None) if network is not loss else None
        if params is not None and not isinstance(params, TensorDictBase):
            params = None
        layers = _linear_layers(network)[:-1]  # the last linear layer is the output head
        for module_path, layer in layers:
            key = tuple(module_path.split(".")) if module_path else ()
            names = ("w1", "w2") if isinstance(layer, LowRankLinear) else ("weight",)
            tensors = []
            for n in names:
                t = params.get(key + (n,), None) if params is not None else None
                tensors.append(t if t is not None else getattr(layer, n))
            if id(tensors[0]) in seen:  # a network reachable under two names (shared parameters)
                continue
            seen.add(id(tensors[0]))
            path = f"{name}.{module_path}"
            if isinstance(layer, LowRankLinear):
                found.append(ParsevalWeight(path, w1=tensors[0], w2=tensors[1]))
            else:
                found.append(ParsevalWeight(path, weight=tensors[0]))
    if not found:
        raise AdaRLValueError(
            f"no hidden linear layers found in {type(loss).__name__}: Parseval regularisation needs networks with "
            "at least two Linear/LowRankLinear layers (hidden + output)"
        )
    return found


class ParsevalRegularizer(nn.Module):
    """``lam * sum_W (base_width / width_W)^2 ||W W^T - s I||_F^2`` over the hidden layers of a loss's networks.

    Call it (no arguments) for the scalar term, or pass a loss output to :meth:`wrap_output` to add it as
    ``"loss_parseval"``. Shapes may change between calls (rank truncation replaces ``.data`` in place); the
    parameter objects are re-read every call.

    With a loss: ``td = reg.wrap_output(sac_loss(batch))`` adds ``td["loss_parseval"]``, to be summed with the loss's
    own ``loss_*`` entries. On a single network:

    >>> from tensordict import TensorDict
    >>> from torchrl.modules import MLP
    >>> net = MLP(in_features=3, out_features=1, num_cells=[2, 2])
    >>> reg = ParsevalRegularizer(net, lam=1e-4, base_width=2)
    >>> reg.layers  # the hidden layers (the output head is left out)
    ['network.0', 'network.2']
    >>> for index in (0, 2):
    ...     _ = nn.init.orthogonal_(net[index].weight, gain=2**0.5)
    >>> round(reg().item(), 6)  # orthogonal rows of squared norm s = 2: no penalty
    0.0
    >>> td = reg.wrap_output(TensorDict({"loss_actor": torch.tensor(1.0)}, []))  # e.g. a SACLoss output
    >>> sorted(td.keys())
    ['loss_actor', 'loss_parseval']
    """

    #: the term reads the parameters alone, never the batch: adarl's fused SAC update adds it (and its gradient)
    #: itself, so a Parseval run keeps the fast path (:func:`adarl.fast.sac.check_fusable_terms`)
    reads_batch = False

    def __init__(
        self,
        loss: nn.Module,
        lam: float = 1e-4,
        s: float = 2.0,
        base_width: int = 64,
        networks: Iterable[str] | None = None,
    ) -> None:
        super().__init__()
        for name, value, ok in (("lam", lam, lam >= 0), ("s", s, s > 0), ("base_width", base_width, base_width >= 1)):
            if isinstance(value, bool) or not ok:
                raise AdaRLValueError(
                    f"ParsevalRegularizer: {name} must be {'>= 0' if name == 'lam' else '> 0'}, got {value!r}"
                )
        self.lam, self.s, self.base_width = float(lam), float(s), int(base_width)
        # not registered as submodules: the loss owns these tensors (and its state_dict saves them)
        self._weights = parseval_weights(loss, networks)

    @property
    def layers(self) -> list[str]:
        """Paths of the regularised layers (``<network>.<module path>``)."""
        return [w.path for w in self._weights]

    def forward(self) -> torch.Tensor:
        total = None
        for w in self._weights:
            term = (self.base_width / w.width) ** 2 * parseval_penalty(w.gram(), self.s)
            total = term if total is None else total + term
        return self.lam * total

    def wrap_output(self, loss_td: TensorDictBase) -> TensorDictBase:
        """Add ``"loss_parseval"`` to a loss module's output TensorDict (in place) and return it."""
        loss_td.set("loss_parseval", self())
        return loss_td

    def extra_repr(self) -> str:
        return f"lam={self.lam:g}, s={self.s:g}, base_width={self.base_width}, layers={len(self._weights)}"


class DiagonalScale(nn.Module):
    """A learnable per-unit gain (initialised to 1) and shift (initialised to 0), ``x * scale + bias``: restores
    the per-unit scale that Parseval's constraint removes from ``W`` (Chung et al.'s optional diagonal layer,
    ``DiagLinear`` in wechu/parseval_reg, which has the same two parameters). ``bias=False`` keeps the gain only."""

    def __init__(self, width: int, device=None, bias: bool = True) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.ones(width, device=device))
        self.bias = nn.Parameter(torch.zeros(width, device=device)) if bias else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale if self.bias is None else x * self.scale + self.bias


class InputScale(nn.Module):
    """One learnable scalar multiplying the network input (initialised to 1), Chung et al.'s input scale."""

    def __init__(self, device=None) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.ones((), device=device))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale


def _parseval_layers(mlp_config, algorithm_config, action_dim: int) -> dict:
    """``algorithm.parseval.{diagonal, input_scale}``: Parseval's optional scale layers in every network."""
    pv = algorithm_config.parseval
    out = {}
    if pv.enabled and pv.diagonal:
        out["diagonal_scale"] = True
    if pv.enabled and pv.input_scale:
        out["input_scale"] = True
    return out


def _parseval_term(loss: nn.Module, algorithm_config) -> ParsevalRegularizer | None:
    """``algorithm.parseval``: the Parseval term on the loss's networks, when enabled."""
    pv = algorithm_config.parseval
    return ParsevalRegularizer(loss, lam=pv.lam, s=pv.s, base_width=pv.base_width) if pv.enabled else None


register_network_variant("parseval", _parseval_layers)
register_loss_term("parseval", _parseval_term)
