"""The acceptance step of Algorithm 1: a lower rank is kept only if the truncated network still fits.

Paper Sec. 4.2: "starting from a high-rank model, we gradually reduce the rank until reaching a stable value" and
"if no lower-rank model with sufficient approximation quality can be found, we simply retain the previous rank,
r_new = r_old". Eq. 10 only *proposes* a candidate rank (read literally it proposes at most ``r - 1`` at every
event, whatever the spectrum, see :class:`adarl.core.rank.EnergyRule`); the first term of Eq. 8, the distance between
the projected and the current policy on state-action samples, decides whether the candidate is good enough.

:class:`ProjectionAcceptance` is that decision. At an event, :class:`adarl.RankAdapter` measures, for each layer
and candidate rank ``k``, the **relative output error** of the layer's network with the layer projected to rank
``k``::

    error(k) = mean_x || f_k(x) - f(x) ||_2 / mean_x || f(x) - mean_x f(x) ||_2

on a batch of recent transitions (:class:`RecentTransitions`): the actor's distribution parameters (``loc`` and
``scale`` of SAC's TanhNormal) on recent states, or each critic's Q-values on recent (state, action) pairs
(an ensemble is as good as its worst member). The change is measured against how much the outputs vary over the
batch, so a constant offset (Q-values in the hundreds) does not hide it. The candidate is accepted when ``error <= tol``
of the network's role (``actor_tol`` / ``critic_tol``). Otherwise, with ``search=True`` (default), the ranks between the
candidate and ``r - 1`` are searched (bisection) for the smallest one within the tolerance, and if even ``r - 1`` is
not, the layer keeps ``r``. Layers of one network are decided in order, each measured with the truncations already
accepted for the earlier layers in place, so the tolerance bounds the whole network's change at the event.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.writers import RoundRobinWriter

from adarl.errors import AdaRLValueError

__all__ = [
    "ProjectionAcceptance",
    "AcceptanceResult",
    "RecentTransitions",
    "recent_transitions",
    "relative_output_error",
    "ACCEPT_MODES",
]

#: Recipe values of ``rank.accept.mode``: ``projection`` (Algorithm 1 as the text describes it) or ``always``
#: (every candidate of the rule is applied: Eq. 10 alone, the literal ratchet).
ACCEPT_MODES = ("projection", "always")


def relative_output_error(output: torch.Tensor, reference: torch.Tensor) -> float:
    """``mean_i ||output_i - reference_i|| / mean_i ||reference_i - mean(reference)||`` over the rows (float64).

    The change is measured against how much the reference varies over the batch, not against its size: what a
    network computes from its input is its variation; a constant offset (Q-values of a few hundred, a policy's
    saturated mean) would make any change look small. ``0`` when the two are equal, ``inf`` when they differ and
    the reference does not vary, ``nan`` on non-finite input (which no tolerance accepts).
    """
    out = output.detach().to(torch.float64).reshape(output.shape[0], -1)
    ref = reference.detach().to(torch.float64).reshape(reference.shape[0], -1)
    diff = float((out - ref).norm(dim=-1).mean())
    spread = float((ref - ref.mean(0, keepdim=True)).norm(dim=-1).mean())
    if not (math.isfinite(diff) and math.isfinite(spread)):
        return float("nan")
    if spread == 0.0:
        return 0.0 if diff == 0.0 else math.inf
    return diff / spread


def _check_tol(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise AdaRLValueError(
            f"ProjectionAcceptance: {name} must be a finite number >= 0 (a relative output error, "
            f"e.g. 0.05 = 5%), got {value!r}"
        )
    return float(value)


@dataclass(frozen=True)
class AcceptanceResult:
    """What the acceptance step decided for one layer.

    ``rank`` is the rank applied (``current`` when refused); ``error`` the relative output error at that rank
    (0 when kept); ``tried`` every ``(rank, error)`` measured, in the order measured; ``reason`` says why the
    candidate was not applied as proposed (``None`` when it was).
    """

    rank: int
    candidate: int
    current: int
    candidate_error: float
    error: float
    tolerance: float
    tried: list = field(default_factory=list)
    reason: str | None = None

    @property
    def accepted(self) -> bool:
        """Whether the rule's candidate was applied as proposed."""
        return self.rank == self.candidate


class ProjectionAcceptance:
    """Accept a candidate rank only if the truncated network stays within a relative output error of the current one.

    Args:
        actor_tol: largest relative change of the actor's outputs (distribution parameters) accepted at an event.
        critic_tol: the same for each critic's Q-values (the worst ensemble member counts).
            The defaults were chosen by measurement (benchmarks/acceptance_calibration.py, docs/rank-rules.md): on
            trained Hopper networks, truncations within 0.05 cost the actor at most 0.1% of its nominal return,
            and a critic's TD loss grows 5x at 0.07 but at most 1.2x within 0.02.
        search: when the candidate is refused, bisect the ranks between it and ``r - 1`` for the smallest one
            within the tolerance (the paper's "no lower-rank model ... can be found"); ``False`` keeps ``r`` as
            soon as the candidate is refused.

    The bisection assumes the error falls as the rank grows (it does for the weight, by Eckart-Young, and in
    practice for the outputs); every rank it measures is recorded, and the rank it returns was measured within
    the tolerance.

    >>> acceptance = ProjectionAcceptance(actor_tol=0.05)
    >>> errors = {2: 0.3, 3: 0.12, 4: 0.06, 5: 0.04, 6: 0.02, 7: 0.01}  # error_at(k): the network at rank k
    >>> result = acceptance.resolve(candidate=2, current=8, error_at=errors.get, role="actor")
    >>> result.rank, result.accepted, result.tried
    (5, False, [(2, 0.3), (5, 0.04), (3, 0.12), (4, 0.06)])
    >>> result.reason
    'candidate 2 changes the actor by 0.3 > tolerance 0.05; rank 5 is within it (0.04)'
    """

    def __init__(self, actor_tol: float = 0.05, critic_tol: float = 0.02, *, search: bool = True) -> None:
        self.actor_tol = _check_tol("actor_tol", actor_tol)
        self.critic_tol = _check_tol("critic_tol", critic_tol)
        if not isinstance(search, bool):
            raise AdaRLValueError(f"ProjectionAcceptance: search must be true or false, got {search!r}")
        self.search = search

    def tolerance(self, role: str) -> float:
        """The tolerance of a network role (``"actor"`` or ``"critic"``)."""
        if role not in ("actor", "critic"):
            raise AdaRLValueError(f"role must be 'actor' or 'critic', got {role!r}")
        return self.actor_tol if role == "actor" else self.critic_tol

    def resolve(self, candidate: int, current: int, error_at: Callable[[int], float], role: str) -> AcceptanceResult:
        """Decide the rank for a layer at ``current`` whose rule proposed ``candidate`` (< ``current``).

        ``error_at(k)`` is the relative output error of the network with the layer projected to rank ``k``.
        """
        if not 1 <= candidate < current:
            raise AdaRLValueError(f"candidate must be in [1, current - 1] = [1, {current - 1}], got {candidate}")
        tol = self.tolerance(role)
        tried: list[tuple[int, float]] = []

        def err(k: int) -> float:
            e = float(error_at(k))
            tried.append((k, e))
            return e

        cand_err = err(candidate)
        if cand_err <= tol:
            return AcceptanceResult(candidate, candidate, current, cand_err, cand_err, tol, tried)
        why = f"candidate {candidate} changes the {role} by {cand_err:.3g} > tolerance {tol:.3g}"
        if not self.search or candidate == current - 1:
            return AcceptanceResult(
                current, candidate, current, cand_err, 0.0, tol, tried, f"{why}; kept rank {current}"
            )
        lo, hi, hi_err = candidate, current, 0.0  # err(lo) > tol, err(hi) <= tol (hi = current: no change)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            e = err(mid)
            if e <= tol:
                hi, hi_err = mid, e
            else:
                lo = mid
        if hi == current:
            return AcceptanceResult(
                current,
                candidate,
                current,
                cand_err,
                0.0,
                tol,
                tried,
                f"{why}, and so does every rank up to {current - 1}; kept rank {current}",
            )
        return AcceptanceResult(
            hi, candidate, current, cand_err, hi_err, tol, tried, f"{why}; rank {hi} is within it ({hi_err:.3g})"
        )

    def __repr__(self) -> str:
        return f"ProjectionAcceptance(actor_tol={self.actor_tol}, critic_tol={self.critic_tol}, search={self.search})"


def recent_transitions(replay_buffer, n: int) -> TensorDictBase:
    """The ``n`` transitions most recently written to a TorchRL replay buffer (fewer if it holds fewer).

    Recent, not uniform: the acceptance step asks whether the truncated network still fits what the current policy
    does now, and the oldest transitions of a 1e6 buffer come from a policy long gone. Works with the round-robin
    writer every TorchRL buffer uses by default (wrap-around included); refuses other writers, whose storage order
    says nothing about recency.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise AdaRLValueError(f"recent_transitions: n must be an integer >= 1, got {n!r}")
    writer = getattr(replay_buffer, "_writer", None)
    if not isinstance(writer, RoundRobinWriter):
        raise AdaRLValueError(
            f"recent_transitions needs a replay buffer with TorchRL's RoundRobinWriter (the default) to know which "
            f"transitions are recent; got writer {type(writer).__name__}. Pass your own callable as fit_data instead"
        )
    size = len(replay_buffer)
    if size == 0:
        raise AdaRLValueError("recent_transitions: the replay buffer is empty (nothing to measure the truncation on)")
    capacity = int(replay_buffer.storage.max_size)
    # The writer's cursor is the slot written next. (Not write_count % capacity: ReplayWarmStart empties the buffer
    # keeping write_count, which TorchRL collectors gate their random phase on, and the cursor restarts at 0.)
    cursor = int(writer._cursor)
    take = min(n, size)
    idx = (cursor - 1 - torch.arange(take)) % capacity
    batch = replay_buffer[idx.flip(0)]
    if isinstance(batch, tuple):
        batch = batch[0]
    return batch


class RecentTransitions:
    """A ``fit_data`` source for :class:`adarl.RankAdapter`: ``recent_transitions(replay_buffer, n)`` when called."""

    def __init__(self, replay_buffer, n: int = 2048) -> None:
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise AdaRLValueError(f"RecentTransitions: n must be an integer >= 1, got {n!r}")
        self.replay_buffer = replay_buffer
        self.n = n

    def __call__(self) -> TensorDictBase:
        return recent_transitions(self.replay_buffer, self.n)

    def __repr__(self) -> str:
        return f"RecentTransitions(n={self.n})"
