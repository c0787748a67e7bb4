"""An exported policy (``adarl export``) in your own code: :class:`ExportedPolicy`, with SB3's ``predict``.

This module imports torch, numpy, the standard library and adarl's errors and file checks only (not TorchRL,
tensordict, gymnasium or the rest of adarl), so a deployment that installs adarl just for it stays light; without
adarl at all, load the file with torch alone (docs/quickstart.md, "Deploy a policy" shows both).

What a file holds: the deterministic actor as one program (observation in, action out, the action scaled to the
env's bounds) and ``adarl.json``, the metadata :func:`adarl.export_policy` wrote next to it inside the archive
(shapes, bounds, ranks, which layers were merged, the run it came from). A TorchScript file (``.pt``) and a
``torch.export`` archive (``.pt2``) are both zip files, so the metadata is read without loading the program.

Loading runs nothing from the file: it is checked first (zip CRCs, the sha256 of each member recorded at export, and
for a ``.pt2`` everything ``torch.export.load`` would otherwise unpickle, evaluate or execute), and a file that is
empty, truncated, corrupt, changed since export or holding code is refused by name
(:class:`~adarl.errors.ExportFileError`); :mod:`adarl.runtime._export_archive` says how.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from adarl.errors import ExportFileError
from adarl.runtime._export_archive import METADATA_FILE, load_program, read_export

__all__ = ["ExportedPolicy", "read_export_metadata", "METADATA_FILE"]


def read_export_metadata(path: str | os.PathLike) -> dict:
    """The ``adarl.json`` metadata of an exported TorchScript or ``torch.export`` file, without loading its program
    (the file is checked first: an empty, truncated, corrupt or changed one is refused, :class:`ExportFileError`)."""
    archive = read_export(path)
    return archive.metadata


class ExportedPolicy:
    """A policy file written by ``adarl export`` / :func:`adarl.export_policy`, ready to act on numpy observations.

    >>> policy = ExportedPolicy("policy.pt")                        # doctest: +SKIP
    >>> action, _ = policy.predict(obs)                             # doctest: +SKIP

    ``predict`` follows Stable-Baselines3's ``model.predict``: one observation (shape ``observation_shape``) gives
    one action, a batch (``(n, *observation_shape)``) gives ``n``; it returns ``(actions, None)`` (no recurrent
    state). Box actions are float32 arrays already inside the env's bounds; a discrete policy's actions are the
    indices ``env.step`` takes (the program itself outputs the one-hot vector TorchRL's actor returns).
    Calling the object on a tensor runs the program itself (``policy(obs_tensor) -> action_tensor``).

    Only TorchScript (``.pt``) and ``torch.export`` (``.pt2``) files load here; an ``.onnx`` file is for an ONNX
    runtime (``onnxruntime.InferenceSession(path).run(None, {"observation": obs})``). Nothing in the file runs while
    it loads; one that is empty, truncated, corrupt, changed since export or holding code is refused by name
    (:class:`~adarl.errors.ExportFileError`, a ``ValueError``).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        p = Path(path)
        archive = read_export(p, onnx_ok=True)  # read once, checked; the program is loaded from these bytes
        if archive is None:
            raise ExportFileError(
                f"{str(p)!r} is an ONNX file: run it with an ONNX runtime, e.g. "
                "onnxruntime.InferenceSession(path).run(None, {'observation': obs}); ExportedPolicy loads .pt and .pt2",
                path=p,
                reason="is an ONNX file",
            )
        self.path, self.format, self.metadata = p, archive.kind, archive.metadata
        try:
            self.observation_shape = tuple(int(n) for n in self.metadata["observation_shape"])
            self.action_shape = tuple(int(n) for n in self.metadata["action_shape"])
            self.action_kind = str(self.metadata["action_kind"])
        except (KeyError, TypeError, ValueError):
            raise ExportFileError(
                f"exported policy {str(p)!r} has incomplete metadata (observation_shape, action_shape, action_kind)",
                path=p,
                reason="incomplete metadata",
            ) from None
        self.program = load_program(archive)
        for t in self.program.parameters():  # torch.export's module gives them back requiring grad
            t.requires_grad_(False)

    def __call__(self, observation: torch.Tensor) -> torch.Tensor:
        """The program on a float32 tensor of shape ``(*leading, *observation_shape)``, any leading dimensions,
        none included: one observation gives one action (the ``.pt2`` program takes ``(batch, obs)`` only and
        raised IndexError on one observation; it is given a batch of one)."""
        shape = tuple(self.observation_shape)
        got = tuple(observation.shape)
        if got[len(got) - len(shape) :] != shape or len(got) < len(shape):
            raise ValueError(f"observation of shape {got}: this policy takes (..., {', '.join(map(str, shape))})")
        leading = got[: len(got) - len(shape)]
        with torch.no_grad():
            out = self.program(observation.reshape(-1, *shape))
        return out.reshape(*leading, *out.shape[1:])

    def predict(
        self,
        observation: np.ndarray,
        state: object = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """The deterministic action(s) for ``observation`` as a numpy array, and ``None`` (SB3's signature).

        ``state`` and ``episode_start`` are accepted for SB3's signature and ignored (the policy has no recurrent
        state). ``deterministic=False`` is refused: the file holds the deterministic actor only (the mean action,
        as adarl's evaluations use); sample with ``adarl.load_policy`` under TorchRL's ``set_exploration_type``.
        """
        if not deterministic:
            raise ValueError(
                "the exported program is the deterministic actor (the action adarl's evaluations take); "
                "for sampled actions use adarl.load_policy(run) under torchrl's set_exploration_type(RANDOM)"
            )
        obs = np.asarray(observation, dtype=np.float32)
        if obs.shape != self.observation_shape and not (
            obs.ndim == len(self.observation_shape) + 1 and obs.shape[1:] == self.observation_shape
        ):
            raise ValueError(
                f"observation of shape {obs.shape}: this policy takes {self.observation_shape} "
                f"or a batch (n, {', '.join(map(str, self.observation_shape))})"
            )
        action = self(torch.from_numpy(np.ascontiguousarray(obs))).numpy()  # one observation or a batch: __call__
        if self.action_kind != "box":
            action = action.argmax(-1)
        return action, None

    def __repr__(self) -> str:
        m = self.metadata
        ranks = ", ".join(f"{x['name']}: rank {x['rank']} {x['form']}" for x in m.get("layers", []) if "rank" in x)
        return (
            f"ExportedPolicy({str(self.path)!r}, format={self.format!r}, observation_shape={self.observation_shape}, "
            f"action_shape={self.action_shape}, env={m.get('env_id')!r}" + (f", {ranks}" if ranks else "") + ")"
        )
