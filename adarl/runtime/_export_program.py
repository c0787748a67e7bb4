"""The deterministic action of a TorchRL actor as plain torch layers: :func:`deterministic_program` (used by
:mod:`adarl.runtime.export`, which checks and writes it).

Why a module of its own: turning the actor (its MLP, low-rank layers, head and distribution) into a scriptable
program is one job; checking it against the actor and writing it in a format is the other (export.py).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import torch
from tensordict.nn import AddStateIndependentNormalScale, NormalParamExtractor
from torch import nn
from torchrl.modules import MLP, OneHotCategorical, TanhModule, TanhNormal

from adarl.baselines.mlp import BaselineMLP
from adarl.baselines.normalization import RunningObsNorm
from adarl.baselines.policy import ClippedNormal
from adarl.core.lowrank import LowRankLinear
from adarl.envs.obs_norm import ObservationAffine
from adarl.errors import AdaRLValueError, one_of

__all__ = ["deterministic_program", "Program", "LayerChoice", "LAYER_FORMS", "CALL_COST_MACS"]

#: ``layers=``: per LowRankLinear, by multiply-adds (``auto``), or all ``merged`` / all ``factored``
LAYER_FORMS = ("auto", "merged", "factored")
#: what a factored layer's second Linear call costs at batch 1, in multiply-adds: ~3-5 us of call overhead at the
#: ~6-9 multiply-adds per ns a one-thread CPU matvec runs here (benchmarks/export_speed.py; docs/performance.md).
#: It keeps small layers (every 64-wide one, an 11 -> 256 input layer) merged, where two calls cost more than the
#: multiply-adds they save, and factors a 256x256 layer below rank ~96, a 1024x1024 one below ~500.
CALL_COST_MACS = 16384

# --- the program's layers: plain torch, scriptable, exportable -------------------------------------------------


class _Float32(nn.Module):
    """The observation as float32 (a gymnasium observation is float64); a no-op on float32 input."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.to(torch.float32)


class _ObsNorm(nn.Module):
    """:class:`~adarl.baselines.normalization.RunningObsNorm` frozen: ``(x - mean) / (std + eps)`` in float32,
    the same float32 operations on the same float32 constants as the live module."""

    def __init__(self, norm: RunningObsNorm) -> None:
        super().__init__()
        self.register_buffer("mean", norm.mean.detach().to(torch.float32).clone())
        self.register_buffer("denominator", norm.std.detach().to(torch.float32) + norm.eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.denominator


class _SafeTanh(nn.Module):
    """TorchRL's ``safetanh_noeps``: ``tanh(x)`` clamped to ``+-(1 - resolution)`` (TanhNormal's transform)."""

    __constants__ = ["limit"]

    def __init__(self, limit: float) -> None:
        super().__init__()
        self.limit = float(limit)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(x).clamp(-self.limit, self.limit)


class _Tanh(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(x)


class _Affine(nn.Module):
    """``loc + scale * x``: TanhNormal's map of ``[-1, 1]`` onto the action box (torch's ``AffineTransform``)."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("loc", loc.detach().clone())
        self.register_buffer("scale", scale.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.loc + self.scale * x


class _Clamp(nn.Module):
    """RNAC's clipped Gaussian's deterministic action: the mean clamped to the box."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low.detach().clone())
        self.register_buffer("high", high.detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp(x, self.low, self.high)


class _BoxTanh(nn.Module):
    """TorchRL's ``TanhModule`` (TD3's and DDPG's deterministic head): ``low + (high - low) * (tanh(x) + 1) / 2``,
    ``tanh(x)`` first clamped to ``+-(1 - resolution)`` when the module clamps. TorchRL applies the map even on the
    ``[-1, 1]`` box (its ``non_trivial`` test is a dict, always true), and so does this, for the same rounding."""

    __constants__ = ["limit"]

    def __init__(self, low: torch.Tensor, high: torch.Tensor, limit: float) -> None:
        super().__init__()
        self.register_buffer("low", low.detach().clone())
        self.register_buffer("high", high.detach().clone())
        self.limit = float(limit)  # 1.0: no clamp

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.tanh(x)
        if self.limit < 1.0:
            x = x.clamp(-self.limit, self.limit)
        return self.low + (self.high - self.low) * (x + 1) / 2


class _OneHotMode(nn.Module):
    """TorchRL's ``OneHotCategorical.mode``: 1 where the logits are largest (int64, the actor's action)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x == x.max(dim=-1, keepdim=True)[0]).to(torch.long)


class _Take(nn.Module):
    """The first ``n`` entries of the last dimension (the ``loc`` half of a head whose last layer is not linear)."""

    __constants__ = ["n"]

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = int(n)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., : self.n]


# --- from the TorchRL actor to the program ----------------------------------------------------------------------


@dataclass
class LayerChoice:
    """How one LowRankLinear of the actor was written: ``form`` is ``merged`` or ``factored``. ``name``:
    ``layer<i>``, ``i`` counting the network's linear layers from the input (a run's ``actor.layer<i>``);
    ``module``: its path in the actor's network."""

    name: str
    module: str
    in_features: int
    out_features: int
    rank: int
    max_rank: int
    form: str

    @property
    def macs(self) -> int:
        """Multiply-adds per observation in the chosen form (the bias add not counted)."""
        if self.form == "merged":
            return self.in_features * self.out_features
        return self.rank * (self.in_features + self.out_features)

    def as_dict(self) -> dict:
        return {**self.__dict__, "macs": self.macs}


@dataclass
class Program:
    """:func:`deterministic_program`'s answer: the module and what the metadata says about it."""

    module: nn.Module
    policy: str
    action_kind: str
    observation_dim: int
    action_dim: int
    action_low: list[float] | None
    action_high: list[float] | None
    layers: list[LayerChoice] = field(default_factory=list)
    observation_normalisation: dict | None = None


def _choose_form(layer: LowRankLinear, layers: str) -> str:
    """``factored`` where ``r (in + out) + CALL_COST_MACS < in out`` (``auto``), else ``merged``; or as asked."""
    if layers != "auto":
        return layers
    factored = layer.rank * (layer.in_features + layer.out_features) + CALL_COST_MACS
    return "factored" if factored < layer.in_features * layer.out_features else "merged"


def _low_rank(layer: LowRankLinear, form: str) -> nn.Module:
    if layer.w1.dim() != 2:
        raise AdaRLValueError("a LowRankLinear with stacked (ensemble) factors cannot be exported as one policy layer")
    bias = layer.bias is not None
    if form == "merged":
        out = nn.Linear(layer.in_features, layer.out_features, bias=bias, dtype=layer.w1.dtype)
        # the exact product, rounded once (the actor rounds x W2^T, then that times W1^T)
        out.weight.data = (layer.w1.detach().double() @ layer.w2.detach().double()).to(layer.w1.dtype)
        if bias:
            out.bias.data = layer.bias.detach().clone()
        return out
    first = nn.Linear(layer.in_features, layer.rank, bias=False, dtype=layer.w1.dtype)
    first.weight.data = layer.w2.detach().clone()
    second = nn.Linear(layer.rank, layer.out_features, bias=bias, dtype=layer.w1.dtype)
    second.weight.data = layer.w1.detach().clone()
    if bias:
        second.bias.data = layer.bias.detach().clone()
    return nn.Sequential(first, second)


def _is_chain(m: nn.Module) -> bool:
    """Whether ``m`` just calls its children in order on one input (nn.Sequential's forward)."""
    if isinstance(m, MLP):
        return not m._reshape_out
    if isinstance(m, BaselineMLP):
        return True
    return isinstance(m, nn.Sequential) and type(m).forward is nn.Sequential.forward


def _leaves(module: nn.Module, prefix: str = "") -> list[tuple[str, nn.Module]]:
    if not _is_chain(module):
        return [(prefix, module)]
    out = []
    for name, child in module.named_children():
        out.extend(_leaves(child, f"{prefix}.{name}" if prefix else name))
    return out


def _actor_parts(actor) -> tuple[nn.Module, object]:
    """The network (observation -> distribution parameters) and the distribution module of a ProbabilisticActor."""
    try:
        net_module, dist_module = actor.module[0], actor.module[1]
        net, in_keys = net_module.module, list(net_module.in_keys)
        dist_module.distribution_class  # noqa: B018 - a distribution module has one
    except (AttributeError, IndexError, TypeError):
        raise AdaRLValueError(
            f"cannot export {type(actor).__name__}: export_policy takes adarl's actors (a TorchRL "
            "ProbabilisticActor of one network and its distribution, or TD3's network and TanhModule, as "
            "load_policy returns)"
        ) from None
    if len(actor.module) != 2 or in_keys != ["observation"]:
        raise AdaRLValueError(
            f"cannot export this actor: it reads {in_keys} through {len(actor.module)} modules; export_policy "
            "takes one network on 'observation' followed by its distribution"
        )
    return net, dist_module


def _tanh_head_parts(actor) -> tuple[nn.Module, TanhModule] | None:
    """The network and ``TanhModule`` of a deterministic actor as TD3 and DDPG build it (a ``TensorDictSequential``
    of the network on ``observation`` writing ``param``, then ``TanhModule`` from ``param`` to ``action``); None for
    any other actor."""
    modules = getattr(actor, "module", None)
    if not isinstance(modules, nn.ModuleList) or len(modules) != 2 or not isinstance(modules[1], TanhModule):
        return None
    net_module, head = modules
    if list(getattr(net_module, "in_keys", [])) != ["observation"] or list(head.out_keys) != ["action"]:
        raise AdaRLValueError(
            f"cannot export this actor: its network reads {list(getattr(net_module, 'in_keys', []))} and its "
            f"TanhModule writes {list(head.out_keys)}; export_policy takes one network on 'observation' and a "
            "TanhModule writing 'action'"
        )
    if list(head.in_keys) != list(net_module.out_keys):
        raise AdaRLValueError(
            f"cannot export this actor: its TanhModule reads {list(head.in_keys)}, its network writes "
            f"{list(net_module.out_keys)}"
        )
    return net_module.module, head


def _tanh_head(head: TanhModule, action_dim: int) -> tuple[nn.Module, torch.Tensor, torch.Tensor]:
    """The program's layer for a ``TanhModule`` and its action bounds."""
    low = head.action_low.to(torch.float32)
    high = head.action_high.to(torch.float32)
    limit = 1.0 - torch.finfo(torch.float32).resolution if head.clamp else 1.0
    low, high = (torch.broadcast_to(t, (action_dim,)).clone() for t in (low, high))
    return _BoxTanh(low, high, limit), low, high


def deterministic_program(actor, layers: str = "auto") -> Program:
    """The deterministic action of a TorchRL ``ProbabilisticActor``, or of TD3's and DDPG's network + ``TanhModule``
    (what :func:`adarl.load_policy` returns), as an ``nn.Sequential`` of plain torch layers: float32 observation in,
    action out.

    ``layers``: ``auto`` (each LowRankLinear merged or factored by multiply-adds), ``merged`` or ``factored``.
    Raises :class:`~adarl.errors.AdaRLValueError` naming what it cannot export (a distribution or layer it does
    not know, ``tanh_loc``); every layer it passes through unchanged must be TorchScript-able.
    """
    if layers not in LAYER_FORMS:
        raise AdaRLValueError(f"layers must be one of {one_of(LAYER_FORMS)}, got {layers!r}")
    tanh_head = _tanh_head_parts(actor)
    if tanh_head is not None:  # TD3 / DDPG: the network's output is the pre-tanh action
        net, head = tanh_head
        dist_class, kwargs = None, {}
        spec = head.spec.get("action")  # None for a TanhModule built without one
    else:
        net, dist_module = _actor_parts(actor)
        dist_class, kwargs = dist_module.distribution_class, dict(dist_module.distribution_kwargs or {})
        spec = getattr(actor, "spec", None)
        spec = spec.get("action") if spec is not None and "action" in spec.keys() else spec
    leaves = _leaves(net)
    if not leaves:
        raise AdaRLValueError("cannot export an actor whose network has no layers")

    # the distribution's parameters: drop what only makes the scale
    _, last = leaves[-1]
    if tanh_head is not None:
        halve = False
    elif isinstance(last, NormalParamExtractor):  # (..., 2A) -> loc (first half), scale
        leaves = leaves[:-1]
        halve = True
    elif isinstance(last, AddStateIndependentNormalScale):  # loc passes through, the scale is a parameter
        leaves = leaves[:-1]
        halve = False
    elif issubclass(dist_class, OneHotCategorical):
        halve = False
    else:
        raise AdaRLValueError(
            f"cannot export this actor: its network ends in {type(last).__name__}, not the NormalParamExtractor "
            "or AddStateIndependentNormalScale of a Gaussian head, nor logits of a categorical policy"
        )

    out: list[nn.Module] = [_Float32()]
    choices: list[LayerChoice] = []
    obs_norm = None
    linear = 0  # linear layers seen so far
    for i, (name, leaf) in enumerate(leaves):
        for sub in leaf.modules():
            linear += isinstance(sub, (nn.Linear, LowRankLinear))
        if isinstance(leaf, LowRankLinear):
            form = _choose_form(leaf, layers)
            choices.append(
                LayerChoice(
                    f"layer{linear - 1}", name, leaf.in_features, leaf.out_features, leaf.rank, leaf.max_rank, form
                )
            )
            out.append(_low_rank(leaf, form))
        elif isinstance(leaf, RunningObsNorm):
            if i != 0:
                raise AdaRLValueError(f"cannot export a RunningObsNorm inside the network (at {name!r}), only first")
            count = int(leaf.count)
            obs_norm = {"kind": "running mean/std (baked in)", "count": count, "eps": leaf.eps}
            if count > 0:  # the live module is the identity until its first update
                out.append(_ObsNorm(leaf))
        elif isinstance(leaf, ObservationAffine):  # env.normalize_observations (load_policy puts it first)
            if i != 0:
                raise AdaRLValueError(f"cannot export an observation normaliser inside the network (at {name!r})")
            obs_norm = {"kind": "VecNorm mean/std (frozen, env.normalize_observations)"}
            out.append(copy.deepcopy(leaf))
        elif isinstance(leaf, nn.Linear) and type(leaf) is nn.Linear:
            lin = nn.Linear(leaf.in_features, leaf.out_features, bias=leaf.bias is not None, dtype=leaf.weight.dtype)
            lin.weight.data = leaf.weight.detach().clone()
            if leaf.bias is not None:
                lin.bias.data = leaf.bias.detach().clone()
            out.append(lin)
        else:
            out.append(copy.deepcopy(leaf))

    # the head: keep only the rows of the loc (a Gaussian's first half)
    if halve:
        head = out[-1]
        if type(head) is nn.Linear and head.out_features % 2 == 0:
            n = head.out_features // 2
            lin = nn.Linear(head.in_features, n, bias=head.bias is not None, dtype=head.weight.dtype)
            lin.weight.data = head.weight.detach()[:n].clone()
            if head.bias is not None:
                lin.bias.data = head.bias.detach()[:n].clone()
            out[-1] = lin
            action_dim = n
        else:
            action_dim = int(spec.shape[-1])
            out.append(_Take(action_dim))
    else:
        action_dim = int(spec.shape[-1]) if spec is not None else -1

    low = high = None
    if tanh_head is not None:
        layer, low_t, high_t = _tanh_head(
            tanh_head[1], int(spec.shape[-1]) if spec is not None else _last_out_features(out)
        )
        action_dim = int(low_t.shape[-1])
        out.append(layer)
        policy, action_kind = "deterministic_tanh", "box"
    elif issubclass(dist_class, TanhNormal):
        if kwargs.get("tanh_loc", False):
            raise AdaRLValueError("cannot export a TanhNormal policy with tanh_loc=True (its loc is rescaled)")
        low_t = torch.as_tensor(kwargs.get("low", -1.0), dtype=torch.float32)
        high_t = torch.as_tensor(kwargs.get("high", 1.0), dtype=torch.float32)
        if kwargs.get("safe_tanh", True):
            out.append(_SafeTanh(1.0 - torch.finfo(torch.float32).resolution))
        else:
            out.append(_Tanh())
        if bool((high_t != 1.0).any()) or bool((low_t != -1.0).any()):
            out.append(_Affine((high_t + low_t) / 2, (high_t - low_t) / 2))
        policy, action_kind = "tanh_normal", "box"
    elif issubclass(dist_class, ClippedNormal):
        low_t = torch.as_tensor(kwargs.get("low", -1.0), dtype=torch.float32)
        high_t = torch.as_tensor(kwargs.get("high", 1.0), dtype=torch.float32)
        out.append(_Clamp(low_t, high_t))
        policy, action_kind = "clipped_gaussian", "box"
    elif issubclass(dist_class, OneHotCategorical):
        out.append(_OneHotMode())
        policy, action_kind = "one_hot_categorical", "one_hot"
        low_t = high_t = None
        action_dim = int(spec.space.n) if spec is not None else -1
    else:
        raise AdaRLValueError(
            f"cannot export a policy with distribution {dist_class.__name__}: supported are TanhNormal (SAC), "
            "a TanhModule head (TD3, DDPG), "
            "ClippedNormal (RNAC's PPO) and OneHotCategorical (discrete SAC)"
        )
    if low_t is not None:
        shape = (action_dim,)
        low = torch.broadcast_to(low_t, shape).tolist()
        high = torch.broadcast_to(high_t, shape).tolist()
    module = nn.Sequential(*out).eval().requires_grad_(False)
    obs_dim = _observation_dim(module)
    return Program(module, policy, action_kind, obs_dim, action_dim, low, high, choices, obs_norm)


def _last_out_features(layers: list[nn.Module]) -> int:
    """The output size of the program's last linear layer (a deterministic head's action size)."""
    for layer in reversed(layers):
        for m in reversed(list(layer.modules())):
            if isinstance(m, nn.Linear):
                return int(m.out_features)
    raise AdaRLValueError("cannot tell the actor's action size: its network has no linear layer")


def _observation_dim(module: nn.Module) -> int:
    """The observation size the program's first layer takes."""
    for m in module.modules():
        if isinstance(m, _ObsNorm):
            return int(m.mean.shape[-1])
        if isinstance(m, ObservationAffine):
            return int(m.loc.shape[-1])
        if isinstance(m, nn.Linear):
            return int(m.in_features)
    raise AdaRLValueError("cannot tell the actor's observation size: its network has no linear layer")
