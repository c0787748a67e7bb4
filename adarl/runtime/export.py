"""A trained policy as a self-contained program for deployment: :func:`export_policy` (``adarl export RUN``).

Why: the TorchRL actor :func:`adarl.load_policy` returns spends most of a batch-1 call in TensorDict's module
machinery (~230 of ~283 us here), so a truncated actor is no faster to *use* than the full one. The export keeps
only what the deterministic action needs, as plain torch layers, and writes one file that torch alone loads (no
adarl, TorchRL or tensordict):

* the actor's network, each :class:`~adarl.core.lowrank.LowRankLinear` either **merged** (``W1 @ W2`` as one
  ``nn.Linear``) or **factored** (two ``nn.Linear``, the bottleneck without bias), whichever is cheaper at its
  rank: factored where ``r (in + out) + CALL_COST_MACS < in out`` (multiply-adds, plus what the second call costs
  at batch 1), or as asked (``layers=``);
* the distribution's deterministic action, as the actor computes it outside ``set_exploration_type``:
  TanhNormal's ``tanh(loc)`` (clamped as TorchRL's safe tanh does) mapped affinely onto the action box, RNAC's
  clipped Gaussian's ``clamp(loc, low, high)``, a discrete policy's one-hot arg-max; the output rows of the head
  that only feed the scale are dropped;
* the PPO baselines' running observation normalisation, baked in with the statistics of the checkpoint.

Every export is checked before it is written: the program's actions on 256 observations must equal the TorchRL
actor's to fp tolerance (merged layers round differently from factored ones; factored layers run the same
operations), else nothing is written. Formats (``format=``): ``torchscript`` (default; ``.pt``, ``torch.jit.load``),
``export`` (``.pt2``, ``torch.export.load(path).module()``) and ``onnx`` (needs the ``onnx`` and ``onnxscript``
packages). docs/performance.md, "Deploying a policy", says why TorchScript is the default and measures them.
"""

from __future__ import annotations

import copy
import importlib.util
import io
import json
import os
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import AddStateIndependentNormalScale, NormalParamExtractor
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, OneHotCategorical, TanhNormal

import adarl
from adarl.baselines.mlp import BaselineMLP
from adarl.baselines.normalization import RunningObsNorm
from adarl.baselines.policy import ClippedNormal
from adarl.core.lowrank import LowRankLinear
from adarl.errors import AdaRLError, AdaRLValueError, one_of
from adarl.runtime.exported import METADATA_FILE
from adarl.runtime.policy import load_policy_with_info

__all__ = [
    "export_policy",
    "export_actor",
    "deterministic_program",
    "ExportResult",
    "FORMATS",
    "SUFFIXES",
    "LAYER_FORMS",
]

#: ``format=`` values and the file suffix each gets by default
FORMATS = ("torchscript", "export", "onnx")
SUFFIXES = {"torchscript": ".pt", "export": ".pt2", "onnx": ".onnx"}
#: ``layers=``: per LowRankLinear, by multiply-adds (``auto``), or all ``merged`` / all ``factored``
LAYER_FORMS = ("auto", "merged", "factored")
#: observations the export is checked on, and the tolerance of the check (actions; logits for a discrete policy)
CHECK_OBSERVATIONS = 256
CHECK_ATOL = 1e-5
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
            "ProbabilisticActor of one network and its distribution, as load_policy returns)"
        ) from None
    if len(actor.module) != 2 or in_keys != ["observation"]:
        raise AdaRLValueError(
            f"cannot export this actor: it reads {in_keys} through {len(actor.module)} modules; export_policy "
            "takes one network on 'observation' followed by its distribution"
        )
    return net, dist_module


def deterministic_program(actor, layers: str = "auto") -> Program:
    """The deterministic action of a TorchRL ``ProbabilisticActor`` (what :func:`adarl.load_policy` returns) as an
    ``nn.Sequential`` of plain torch layers: float32 observation in, action out.

    ``layers``: ``auto`` (each LowRankLinear merged or factored by multiply-adds), ``merged`` or ``factored``.
    Raises :class:`~adarl.errors.AdaRLValueError` naming what it cannot export (a distribution or layer it does
    not know, ``tanh_loc``); every layer it passes through unchanged must be TorchScript-able.
    """
    if layers not in LAYER_FORMS:
        raise AdaRLValueError(f"layers must be one of {one_of(LAYER_FORMS)}, got {layers!r}")
    net, dist_module = _actor_parts(actor)
    dist_class, kwargs = dist_module.distribution_class, dict(dist_module.distribution_kwargs or {})
    leaves = _leaves(net)
    if not leaves:
        raise AdaRLValueError("cannot export an actor whose network has no layers")
    spec = getattr(actor, "spec", None)
    spec = spec.get("action") if spec is not None and "action" in spec.keys() else spec

    # the distribution's parameters: drop what only makes the scale
    _, last = leaves[-1]
    if isinstance(last, NormalParamExtractor):  # (..., 2A) -> loc (first half), scale
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
    if issubclass(dist_class, TanhNormal):
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
            "ClippedNormal (RNAC's PPO) and OneHotCategorical (discrete SAC)"
        )
    if low_t is not None:
        shape = (action_dim,)
        low = torch.broadcast_to(low_t, shape).tolist()
        high = torch.broadcast_to(high_t, shape).tolist()
    module = nn.Sequential(*out).eval().requires_grad_(False)
    obs_dim = _observation_dim(module)
    return Program(module, policy, action_kind, obs_dim, action_dim, low, high, choices, obs_norm)


def _observation_dim(module: nn.Module) -> int:
    """The observation size the program's first layer takes."""
    for m in module.modules():
        if isinstance(m, _ObsNorm):
            return int(m.mean.shape[-1])
        if isinstance(m, nn.Linear):
            return int(m.in_features)
    raise AdaRLValueError("cannot tell the actor's observation size: its network has no linear layer")


# --- checking, writing ------------------------------------------------------------------------------------------


def _actor_actions(actor, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return actor(TensorDict(observation=obs, batch_size=obs.shape[:1]))["action"]


def _check_observations(program: Program, n: int = CHECK_OBSERVATIONS) -> torch.Tensor:
    """``n`` observations around the normalisation statistics (or N(0, 2^2)), from a generator of their own."""
    g = torch.Generator().manual_seed(0)
    obs = 2.0 * torch.randn(n, program.observation_dim, generator=g)
    norm = next((m for m in program.module if isinstance(m, _ObsNorm)), None)
    if norm is not None:
        obs = norm.mean + norm.denominator * obs
    return obs


def _check(run_program, program: Program, actor, what: str) -> float:
    """The largest difference between the program's actions and the actor's; raises when above tolerance."""
    obs = _check_observations(program)
    want = _actor_actions(actor, obs)
    with torch.no_grad():
        got = run_program(obs)
    if program.action_kind == "box":
        if got.shape != want.shape:
            raise AdaRLError(f"{what}: its actions have shape {tuple(got.shape)}, the actor's {tuple(want.shape)}")
        diff = float((got - want).abs().max())
        if not diff <= CHECK_ATOL:
            raise AdaRLError(
                f"{what}: its actions differ from the actor's by up to {diff:.3g} (tolerance {CHECK_ATOL:g}) on "
                f"{len(obs)} observations; nothing written"
            )
        return diff
    # discrete: the arg-max may flip only where the actor's two best logits tie to rounding
    with torch.no_grad():
        logits = nn.Sequential(*list(program.module)[:-1])(obs)
        ref = actor.module[0](TensorDict(observation=obs, batch_size=[len(obs)]))["logits"]
    diff = float((logits - ref).abs().max())
    top2 = ref.topk(2, dim=-1).values
    clear = (top2[:, 0] - top2[:, 1]) > 10 * CHECK_ATOL
    if not diff <= CHECK_ATOL or not torch.equal(got[clear], want[clear].to(got.dtype)):
        raise AdaRLError(f"{what}: its actions differ from the actor's (logits by up to {diff:.3g}); nothing written")
    return diff


@dataclass
class ExportResult:
    """What :func:`export_policy` wrote: the file, its format, size and metadata (also inside the file)."""

    path: Path
    format: str
    size_bytes: int
    metadata: dict

    def describe(self) -> str:
        """One line for the terminal."""
        m = self.metadata
        layers = ", ".join(f"{x['name']} rank {x['rank']}/{x['max_rank']} {x['form']}" for x in m["layers"])
        src = f"{m['checkpoint']} ({m['frames']} frames)" if m.get("checkpoint") else "the actor"
        return (
            f"exported the policy of {src} -> {self.path} ({self.format}, {self.size_bytes / 1024:.1f} KiB, "
            f"{m['parameters']} parameters" + (f"; {layers}" if layers else "") + ")"
        )


def _metadata(program: Program, fmt: str, source: dict, check_diff: float | None) -> dict:
    params = sum(t.numel() for t in program.module.state_dict().values())
    return {
        "adarl_export": 1,
        "format": fmt,
        "adarl_version": adarl.__version__,
        "torch_version": torch.__version__,
        **source,
        "policy": program.policy,
        "deterministic": True,
        "input": "observation",
        "output": "action",
        "observation_shape": [program.observation_dim],
        "observation_dtype": "float32",
        "action_kind": program.action_kind,
        "action_shape": [program.action_dim],
        "action_low": program.action_low,
        "action_high": program.action_high,
        "observation_normalisation": program.observation_normalisation,
        "layers": [c.as_dict() for c in program.layers],
        "layer_rule": f"factored where rank * (in + out) + {CALL_COST_MACS} < in * out, else merged (W1 @ W2 as one "
        "Linear); layers='merged'/'factored' override it",
        "parameters": params,
        "check": {
            "observations": CHECK_OBSERVATIONS,
            "max_abs_diff": check_diff,
            "tolerance": CHECK_ATOL,
            "against": "the TorchRL actor's deterministic action (load_policy)",
        },
    }


def _write_atomic(path: Path, write) -> None:
    """``write(tmp_path)``, then rename onto ``path`` (no half-written file under the final name)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _torchscript(program: Program, actor, meta_for) -> tuple[object, float]:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, message=r".*torch\.jit.*")
        try:
            scripted = torch.jit.script(program.module)
        except Exception as err:  # noqa: BLE001 - a layer TorchScript cannot compile: name it
            kinds = sorted({type(m).__name__ for m in program.module.modules()} - {"Sequential"})
            raise AdaRLValueError(
                f"cannot compile the policy to TorchScript ({type(err).__name__}: {str(err).splitlines()[0]}); "
                f"its layers: {', '.join(kinds)}. Try --format export"
            ) from None
    diff = _check(scripted, program, actor, "the TorchScript program")

    def write(tmp: str) -> None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=DeprecationWarning, message=r".*torch\.jit.*")
            torch.jit.save(scripted, tmp, _extra_files={METADATA_FILE: json.dumps(meta_for(diff), indent=1)})

    return write, diff


def _dynamic_batch(program: Program):
    example = _check_observations(program, 2)
    return example, ({0: torch.export.Dim("batch")},)


def _torch_export(program: Program, actor, meta_for) -> tuple[object, float]:
    example, dynamic = _dynamic_batch(program)
    try:
        ep = torch.export.export(program.module, (example,), dynamic_shapes=dynamic)
    except Exception as err:  # noqa: BLE001
        raise AdaRLValueError(
            f"torch.export could not capture the policy ({type(err).__name__}: {str(err).splitlines()[0]}); "
            "try --format torchscript"
        ) from None
    diff = _check(ep.module(), program, actor, "the torch.export program")

    def write(tmp: str) -> None:
        buffer = io.BytesIO()  # torch.export.save wants a buffer or a name ending in .pt2; -o may name any file
        torch.export.save(ep, buffer, extra_files={METADATA_FILE: json.dumps(meta_for(diff), indent=1)})
        Path(tmp).write_bytes(buffer.getvalue())

    return write, diff


def _onnx(program: Program, actor, meta_for) -> tuple[object, float | None]:
    missing = [m for m in ("onnx", "onnxscript") if importlib.util.find_spec(m) is None]
    if missing:
        raise AdaRLValueError(
            f"--format onnx needs the {' and '.join(missing)} package{'s' if len(missing) > 1 else ''} "
            f"(pip install {' '.join(missing)}); use --format torchscript or export without them"
        )
    import onnx

    example, dynamic = _dynamic_batch(program)
    diff = _check(program.module, program, actor, "the policy program")

    def write(tmp: str) -> None:
        torch.onnx.export(
            program.module,
            (example,),
            tmp,
            input_names=["observation"],
            output_names=["action"],
            dynamic_shapes=dynamic,
            dynamo=True,
            external_data=False,
        )
        model = onnx.load(tmp)
        onnx.helper.set_model_props(model, {"adarl": json.dumps(meta_for(diff))})
        onnx.save(model, tmp)

    return write, diff


_WRITERS = {"torchscript": _torchscript, "export": _torch_export, "onnx": _onnx}


def _target(path: str | os.PathLike, overwrite: bool) -> Path:
    p = Path(path)
    if p.is_dir():
        raise AdaRLValueError(f"{str(p)!r} is a folder; give the file to write (e.g. {str(p / 'policy.pt')!r})")
    if p.exists() and not overwrite:
        raise AdaRLValueError(f"{str(p)!r} exists; pass --overwrite (overwrite=True) to replace it")
    if not p.parent.is_dir():
        raise AdaRLValueError(f"{str(p.parent)!r}: no such folder to write {p.name!r} into")
    return p


def export_actor(
    actor,
    path: str | os.PathLike,
    *,
    format: str = "torchscript",
    layers: str = "auto",
    overwrite: bool = False,
    source: dict | None = None,
) -> ExportResult:
    """Write ``actor`` (a TorchRL ``ProbabilisticActor`` as :func:`adarl.load_policy` returns) as a self-contained
    deterministic program; :func:`export_policy` for a run folder. ``source``: extra metadata (where it came from)."""
    if format not in FORMATS:
        raise AdaRLValueError(f"format must be one of {one_of(FORMATS)}, got {format!r}")
    target = _target(path, overwrite)
    program = deterministic_program(actor, layers)
    src = dict(source or {})

    def meta_for(diff):
        return _metadata(program, format, src, diff)

    write, diff = _WRITERS[format](program, actor, meta_for)
    _write_atomic(target, write)
    return ExportResult(target, format, target.stat().st_size, meta_for(diff))


def export_policy(
    run_dir_or_checkpoint: str | os.PathLike,
    path: str | os.PathLike | None = None,
    *,
    which: str = "latest",
    format: str = "torchscript",
    layers: str = "auto",
    overwrite: bool = False,
) -> ExportResult:
    """Export the policy of a run (a run folder or a checkpoint file in one) to ``path`` (default
    ``<run>/policy.pt``, ``.pt2`` or ``.onnx``): a program of the deterministic actor that torch alone loads.

    The file gives the actions :func:`adarl.load_policy` gives (checked on 256 observations before it is written);
    load it with :class:`adarl.ExportedPolicy` (``predict(obs)`` on numpy, as SB3) or with torch alone
    (``torch.jit.load``; ``torch.export.load(path).module()`` for ``format="export"``). ``layers``: ``auto``
    (each low-rank layer merged or factored, whichever is cheaper at its rank: :data:`CALL_COST_MACS`), ``merged`` or
    ``factored``. An existing file is replaced only with ``overwrite=True``.
    """
    if format not in FORMATS:
        raise AdaRLValueError(f"format must be one of {one_of(FORMATS)}, got {format!r}")
    if layers not in LAYER_FORMS:
        raise AdaRLValueError(f"layers must be one of {one_of(LAYER_FORMS)}, got {layers!r}")
    if path is not None:
        _target(path, overwrite)  # before loading: a bad -o fails at once
    loaded = load_policy_with_info(run_dir_or_checkpoint, which)
    target = _target(path if path is not None else Path(loaded.run_dir) / f"policy{SUFFIXES[format]}", overwrite)
    recipe = loaded.recipe
    source = {
        "run_dir": str(Path(loaded.run_dir).resolve()),
        "checkpoint": str(Path(loaded.checkpoint).resolve()),
        "frames": loaded.frames,
        "recipe": recipe.name,
        "algorithm": recipe.algorithm.name,
        "env_id": recipe.env.id,
    }
    try:
        return export_actor(loaded.actor, target, format=format, layers=layers, overwrite=overwrite, source=source)
    except AdaRLValueError as err:
        if str(err).startswith("cannot "):
            raise AdaRLValueError(f"{str(loaded.run_dir)!r} (recipe {recipe.name}): {err}") from None
        raise
