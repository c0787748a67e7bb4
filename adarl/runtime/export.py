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
  clipped Gaussian's ``clamp(loc, low, high)``, a discrete policy's one-hot arg-max; TD3's and DDPG's deterministic
  actor's ``TanhModule``, ``low + (high - low) * (tanh(x) + 1) / 2``; the output rows of the head
  that only feed the scale are dropped;
* the PPO baselines' running observation normalisation, baked in with the statistics of the checkpoint.

Every export is checked before it is written: the program's actions on 256 observations must equal the TorchRL
actor's to fp tolerance (merged layers round differently from factored ones; factored layers run the same
operations), else nothing is written. The file is sealed: its ``adarl.json`` records the sha256 of every other member
of the archive, which :class:`~adarl.runtime.exported.ExportedPolicy` checks (and loads it without running anything
from it: :mod:`adarl.runtime._export_archive`). Formats (``format=``): ``torchscript`` (default; ``.pt``,
``torch.jit.load``), ``export`` (``.pt2``, ``torch.export.load(path).module()``) and ``onnx`` (needs the ``onnx``
and ``onnxscript`` packages). docs/performance.md, "Deploying a policy", says why TorchScript is the default and
measures them.
"""

from __future__ import annotations

import importlib.util
import io
import json
import os
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

import adarl
from adarl.envs.obs_norm import ObservationAffine
from adarl.errors import AdaRLError, AdaRLValueError, ExportFileError, one_of
from adarl.runtime._export_archive import load_program, read_export, seal
from adarl.runtime._export_program import (  # noqa: F401  (CALL_COST_MACS: part of this module's interface)
    CALL_COST_MACS,
    LAYER_FORMS,
    Program,
    _ObsNorm,
    deterministic_program,
)
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
#: observations the export is checked on, and the tolerance of the check (actions; logits for a discrete policy)
CHECK_OBSERVATIONS = 256
CHECK_ATOL = 1e-5


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
    affine = next((m for m in program.module if isinstance(m, ObservationAffine)), None)
    if affine is not None:  # env.normalize_observations
        obs = affine.loc + affine.scale * obs
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
    """``write(tmp_path)``, then rename onto ``path`` (no half-written file under the final name). The temporary name
    is not created beforehand (``mkstemp`` made it 0600, and exports were unreadable to a group that shares runs):
    the file gets the mode the user's umask gives any new file."""
    tmp = str(path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _write_sealed(tmp: str, archive: bytes, metadata: dict) -> None:
    """The archive torch wrote, sealed (adarl.json with the sha256 of every member), written to ``tmp``, then read
    back as :class:`~adarl.runtime.exported.ExportedPolicy` reads it: what is written is known to load."""
    Path(tmp).write_bytes(seal(archive, metadata))
    try:
        load_program(read_export(tmp))
    except ExportFileError as err:  # a program adarl's own loader would refuse: a bug here, said as one
        raise AdaRLError(
            f"the export does not load back through adarl's checks ({err.reason}); nothing written"
        ) from None


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
        buffer = io.BytesIO()
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=DeprecationWarning, message=r".*torch\.jit.*")
            torch.jit.save(scripted, buffer)
        _write_sealed(tmp, buffer.getvalue(), meta_for(diff))

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
        torch.export.save(ep, buffer)
        _write_sealed(tmp, buffer.getvalue(), meta_for(diff))

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
