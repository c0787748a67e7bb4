"""What a rank event did: :class:`LayerRecord` (one layer) and :class:`RankEvent` (one call of ``adapt``).

Plain dataclasses, so that an event is logged, written to ``rank_history.json`` and read back from a checkpoint
(:meth:`RankEvent.from_dict`) without the adapter. Re-exported by :mod:`adarl.core.adapter`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["LayerRecord", "RankEvent"]


@dataclass
class LayerRecord:
    """What one rank event did to one layer.

    For a stacked ensemble, ``singular_values``, ``retained_energy`` and ``truncation_error`` are per member
    (lists), and ``member_ranks`` holds each member's own choice (the layer takes the largest).
    ``retained_energy`` and ``truncation_error`` (``||W - Pi_r(W)||_F``) are at the applied ``new_rank``.
    ``skipped`` is ``None`` when the layer changed, otherwise why not. ``target`` says how the target factors were
    given the new shape (``"sync"``, ``"project"``, ``"sync (fallback: ...)"``) or ``None`` (no target / no change).

    The acceptance step (:mod:`adarl.core.acceptance`) fills the rest: ``candidate`` is the rule's proposal (the
    largest member's), ``candidate_error`` and ``error`` the relative output error of the layer's network with the
    layer at the candidate and at ``new_rank`` (the truncations already accepted for earlier layers of the same
    network in place; ``None`` when nothing was measured, ``0`` when the rank is kept), ``tolerance`` the bound
    (``None`` without an acceptance step: every candidate is applied), ``tried`` every ``[rank, error]``
    measured and ``note`` why a refused candidate led to another rank.
    """

    step: int
    layer: str
    network: str  # "actor" | "critic"
    old_rank: int
    new_rank: int
    singular_values: list
    retained_energy: Any
    truncation_error: Any
    skipped: str | None = None
    member_ranks: list[int] | None = None
    target: str | None = None
    candidate: int | None = None
    candidate_error: float | None = None
    error: float | None = None
    tolerance: float | None = None
    tried: list | None = None
    note: str | None = None
    name: str | None = None  # the layer's human name ("actor.layer0"); ``layer`` keeps the module path

    @property
    def changed(self) -> bool:
        return self.new_rank != self.old_rank

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class RankEvent:
    """One call of :meth:`RankAdapter.adapt`: the optimisation step it ran at and one record per layer."""

    step: int
    index: int
    layers: list[LayerRecord] = field(default_factory=list)
    #: the environment frames the run had collected at the event, when a trainer records them (None: not recorded,
    #: as in histories written before it was); the run's plots put events on this axis
    frames: int | None = None
    #: the adapter that ran the event (``None`` for an event read back from a checkpoint): callbacks such as
    #: :class:`~adarl.core.warmstart.ReplayWarmStart` use it to check that their policy holds the loss's tensors.
    adapter: Any = field(default=None, repr=False, compare=False)

    @property
    def changed(self) -> bool:
        """Whether any layer's rank changed (only then are caches, schedulers and callbacks touched)."""
        return any(r.changed for r in self.layers)

    @property
    def ranks(self) -> dict[str, int]:
        return {r.layer: r.new_rank for r in self.layers}

    def as_dict(self) -> dict:
        out = {"step": self.step, "index": self.index}
        if self.frames is not None:
            out["frames"] = self.frames
        return {**out, "layers": [r.as_dict() for r in self.layers]}

    @classmethod
    def from_dict(cls, d: Mapping, names: Mapping[str, str] | None = None) -> RankEvent:
        """An event from :meth:`as_dict`; ``names`` (``{layer_path: human name}``) fills the names of records saved
        before layers had them."""
        layers = []
        for r in d["layers"]:
            rec = LayerRecord(**r)
            if rec.name is None and names:
                rec.name = names.get(rec.layer)
            layers.append(rec)
        frames = d.get("frames")
        return cls(int(d["step"]), int(d["index"]), layers, None if frames is None else int(frames))
