"""Rank rules: given a layer's singular values, choose its new rank (Algorithm 1, step 6).

Every rule sees the spectrum in float64, never returns more than the current rank (ranks only go down, which is
what makes them settle: paper Lemma 3) nor less than ``min_rank``, and refuses to act on a spectrum that is
non-finite or numerically zero (two zero factors could never train again): it then keeps the rank and says why.
A share or ratio within 1e-12 of ``beta`` counts as equal to it (``beta=0.7`` means 7/10 at any spectrum scale).

=====================  =====================================================================================
``EnergyRule``         paper Eq. 10, literal: the largest ``l`` whose cumulative share ``sum_{i<=l} s_i / sum s``
                       is ``<= beta``. For any ``beta < 1`` this is at most ``r - 1``: every event removes at
                       least one direction, however healthy the spectrum (it *ratchets* down to ``min_rank``).
``InclusiveEnergyRule`` the usual convention (peft, TRP): the smallest ``l`` whose share is ``>= beta``; it keeps
                       the rank when the spectrum is flat enough, so ranks can settle above ``min_rank``.
``RatioRule``          paper Eq. 33 (ablation D.4): the smallest ``l`` with ``s_l / s_1 <= beta``.
``FixedRank``          a given ``target_rank`` (the fixed-rank baseline, or a one-off projection).
``PolicyFitRule``      beyond the paper: solves the upper level of Eq. 8 directly, the smallest ``r`` minimising
                       ``fit(r) + lam * r`` where ``fit(r)`` is the mean distance between the network's output with
                       this layer projected to rank ``r`` and its output now, measured on replay states.
=====================  =====================================================================================
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch

from adarl import plugins
from adarl.errors import AdaRLValueError

__all__ = [
    "RankDecision",
    "RankRule",
    "EnergyRule",
    "InclusiveEnergyRule",
    "RatioRule",
    "FixedRank",
    "PolicyFitRule",
    "registered_rule",
    "make_rule",
    "energy_share",
]

FitFn = Callable[[int], float]

# Shares and ratios within this of beta count as ties (equal to beta): a beta written as a decimal (0.7) means
# the decimal, and float64 rounding of a cumsum must not make the answer depend on the spectrum's scale.
_TIE_TOL = 1e-12


@dataclass(frozen=True)
class RankDecision:
    """What a rule decided for one layer: the new rank, and why it kept the old one if it did."""

    rank: int
    current_rank: int
    retained_energy: float  # sum(s[:rank]) / sum(s), the Eq. 10 share kept
    skipped: str | None = None  # reason the event was skipped (rank kept), or None

    def as_dict(self) -> dict:
        return asdict(self)


def energy_share(s: torch.Tensor, rank: int) -> float:
    """Eq. 10's share ``sum_{i<=rank} s_i / sum_i s_i`` in float64 (``nan`` for a zero spectrum)."""
    s = s.detach().to(torch.float64)
    total = float(s.sum())
    return float(s[:rank].sum()) / total if total > 0 else float("nan")


def _check_unit_interval(name: str, value: float, rule: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < float(value) < 1.0:
        raise AdaRLValueError(f"{rule}: {name} must be a number in the open interval (0, 1), got {value!r}")
    return float(value)


class RankRule(ABC):
    """Base class: validation, float64, clamping to ``[min_rank, current_rank]`` and skip reasons.

    Subclasses implement :meth:`select` on a clean, descending float64 spectrum.
    """

    name: str = "rule"
    needs_fit: bool = False

    def __init__(self, zero_tol: float = 1e-10) -> None:
        self.zero_tol = float(zero_tol)

    def __call__(
        self,
        singular_values: torch.Tensor,
        current_rank: int | None = None,
        *,
        min_rank: int = 1,
        fit: FitFn | None = None,
    ) -> RankDecision:
        s = torch.as_tensor(singular_values).detach().to(torch.float64).flatten()
        current = int(current_rank) if current_rank is not None else s.numel()
        if current < 1:
            raise AdaRLValueError(f"current_rank must be >= 1, got {current}")
        if isinstance(min_rank, bool) or not isinstance(min_rank, int) or min_rank < 1:
            raise AdaRLValueError(f"min_rank must be an integer >= 1, got {min_rank!r}")
        if s.numel() == 0:
            return RankDecision(current, current, float("nan"), "empty spectrum")
        if not bool(torch.isfinite(s).all()):
            return RankDecision(current, current, float("nan"), "non-finite singular values")
        s = s.sort(descending=True).values
        if float(s[0]) <= self.zero_tol:
            return RankDecision(current, current, float("nan"), f"spectrum is ~zero (largest {float(s[0]):.3g})")
        if self.needs_fit and fit is None:
            raise AdaRLValueError(f"{type(self).__name__} needs a fit(rank) -> distance callable")
        chosen = int(self.select(s, current, min_rank, fit))
        floor = min(min_rank, current)
        chosen = max(floor, min(chosen, current))
        return RankDecision(chosen, current, energy_share(s, chosen))

    @abstractmethod
    def select(self, s: torch.Tensor, current_rank: int, min_rank: int, fit: FitFn | None) -> int:
        """Return the raw choice (it is clamped afterwards)."""

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if k != "zero_tol")
        return f"{type(self).__name__}({args})"


class EnergyRule(RankRule):
    """Paper Eq. 10 as written: ``max{l : sum_{i<=l} s_i / sum_i s_i <= beta}`` (ratchets: at most ``r - 1``).

    >>> EnergyRule(beta=0.9)(torch.tensor([5.0, 3.0, 1.0, 0.5, 0.5]), current_rank=5)
    RankDecision(rank=3, current_rank=5, retained_energy=0.9, skipped=None)
    """

    name = "energy"

    def __init__(self, beta: float = 0.98, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        self.beta = _check_unit_interval("beta", beta, type(self).__name__)

    def select(self, s, current_rank, min_rank, fit):
        share = s.cumsum(0) / s.sum()
        # The same tie tolerance as the inclusive rule, so that a share of exactly beta in exact arithmetic
        # counts as <= beta whatever the scale of the spectrum (cumsum of ten 0.1s reaches 0.7000000000000001).
        # The full share is 1 > beta in exact arithmetic, so l = n is never a candidate (for beta within the
        # tolerance of 1 it would otherwise slip in).
        ok = torch.nonzero(share[:-1] <= self.beta + _TIE_TOL).flatten()
        return int(ok[-1]) + 1 if ok.numel() else 0


class InclusiveEnergyRule(RankRule):
    """The smallest ``l`` whose cumulative share reaches ``beta``; keeps the rank when nothing can go."""

    name = "energy_inclusive"

    def __init__(self, beta: float = 0.98, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        self.beta = _check_unit_interval("beta", beta, type(self).__name__)

    def select(self, s, current_rank, min_rank, fit):
        share = s.cumsum(0) / s.sum()
        # A tiny tolerance so that a share of exactly beta in exact arithmetic is not lost to rounding.
        ok = torch.nonzero(share >= self.beta - _TIE_TOL).flatten()
        return int(ok[0]) + 1 if ok.numel() else current_rank


class RatioRule(RankRule):
    """Paper Eq. 33: ``min{l : s_l / s_1 <= beta}``; keeps the rank if no singular value falls that low."""

    name = "ratio"

    def __init__(self, beta: float = 0.98, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        self.beta = _check_unit_interval("beta", beta, type(self).__name__)

    def select(self, s, current_rank, min_rank, fit):
        ok = torch.nonzero(s / s[0] <= self.beta + _TIE_TOL).flatten()
        return int(ok[0]) + 1 if ok.numel() else current_rank


class FixedRank(RankRule):
    """Always ``target_rank`` (clamped to the current rank: rules never grow a layer).

    ``target_rank`` is the recipe's ``rank.target_rank``: one name in Python and in recipes
    (``make_rule("fixed", target_rank=8)``).
    """

    name = "fixed"

    def __init__(self, target_rank: int, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        if isinstance(target_rank, bool) or not isinstance(target_rank, int) or target_rank < 1:
            raise AdaRLValueError(f"FixedRank: target_rank must be an integer >= 1, got {target_rank!r}")
        self.target_rank = target_rank

    def select(self, s, current_rank, min_rank, fit):
        return self.target_rank


class PolicyFitRule(RankRule):
    """Upper level of Eq. 8: ``argmin_r fit(r) + lam * r`` over ``[min_rank, current_rank]`` (smallest on ties).

    ``fit(r)`` is supplied by the caller (:class:`adarl.RankAdapter` measures the mean L2 distance between the
    actor's action distribution parameters, or the critic's Q-values, with the layer projected to rank ``r``
    and as it is now, on a batch of replay states). ``lam`` trades that distance against one unit of rank, so
    its scale is the scale of the network's outputs. ``candidates`` caps how many ranks are tried (evenly
    spread, always including both ends) so a 1024-wide layer does not cost 1024 forward passes.
    """

    name = "policy_fit"
    needs_fit = True

    def __init__(self, lam: float = 1e-3, candidates: int = 64, zero_tol: float = 1e-10) -> None:
        super().__init__(zero_tol)
        if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not lam >= 0 or math.isinf(lam):
            raise AdaRLValueError(f"PolicyFitRule: lam must be a finite number >= 0, got {lam!r}")
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 2:
            raise AdaRLValueError(f"PolicyFitRule: candidates must be an integer >= 2, got {candidates!r}")
        self.lam = float(lam)
        self.candidates = candidates

    def select(self, s, current_rank, min_rank, fit):
        lo = min(min_rank, current_rank)
        ranks = range(lo, current_rank + 1)
        if len(ranks) > self.candidates:
            grid = torch.linspace(lo, current_rank, self.candidates).round().long().unique().tolist()
            ranks = sorted(set(grid))
        best_rank, best_cost = current_rank, math.inf
        for r in ranks:
            d = float(fit(int(r)))
            if not math.isfinite(d):
                continue
            cost = d + self.lam * r
            if cost < best_cost - 1e-15:
                best_rank, best_cost = int(r), cost
        return best_rank


def registered_rule(name: str, *, spec: bool = False):
    """The :class:`RankRule` subclass registered as ``name`` in the one table of rules,
    :data:`adarl.plugins.RANK_RULES` (adarl's five, declared there by path as a plugin's would be, and every
    registered or installed plugin's), checked here once for every caller: :func:`make_rule` and a recipe's
    ``rank`` section (``spec=True``: ``(class, its RankRuleSpec)``). An unknown name lists the registered ones.

    That module imports neither torch nor anything of core (it names core's rules by ``"module:Class"`` path), so
    this is no import cycle (tests/test_architecture.py)."""
    entry = plugins.rank_rule(name)
    cls = entry.rule_class()
    if not (isinstance(cls, type) and issubclass(cls, RankRule)):
        provider = entry.provider or ("adarl" if entry.builtin else "a register_rank_rule call")
        raise AdaRLValueError(
            f"rank rule {name!r} ({entry.rule_path}, from {provider}) is registered as {cls!r}, which is not an "
            "adarl.core.rank.RankRule subclass"
        )
    return (cls, entry) if spec else cls


def make_rule(name: str, **kwargs) -> RankRule:
    """Build a rule by its registered name (``energy``, ``energy_inclusive``, ``ratio``, ``fixed``, ``policy_fit``,
    or one registered with :func:`adarl.register_rank_rule`, installed plugins included) with ``kwargs``."""
    cls = registered_rule(name)
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise AdaRLValueError(f"rank rule {name!r}: {err}") from None
