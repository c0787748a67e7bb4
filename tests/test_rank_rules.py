"""Rank rules (paper Eq. 10, Eq. 33, Eq. 8's upper level) on hand-computed spectra, plus property tests.

The property tests compare against EXACT rational arithmetic (``fractions.Fraction`` over the float64 values),
not against the rule's own float64 cumsum, so they are an independent reference.
"""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from adarl import plugins
from adarl.core.rank import (
    EnergyRule,
    FixedRank,
    InclusiveEnergyRule,
    PolicyFitRule,
    RankDecision,
    RatioRule,
    energy_share,
    make_rule,
)
from adarl.errors import AdaRLValueError

S4321 = torch.tensor([4.0, 3.0, 2.0, 1.0])  # shares 0.4, 0.7, 0.9, 1.0


def t(values, dtype=torch.float64):
    return torch.tensor(values, dtype=dtype)


def exact_shares(s: list[float]) -> list[Fraction]:
    """Cumulative shares in exact arithmetic, share[l-1] = sum_{i<=l} s_i / sum s."""
    fr = [Fraction(x) for x in s]
    total = sum(fr)
    out, acc = [], Fraction(0)
    for x in fr:
        acc += x
        out.append(acc / total)
    return out


# ---------------------------------------------------------------------------------------------------------
# Eq. 10, literal and inclusive, on hand-computed spectra
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "beta,literal,inclusive",
    [
        (0.3, 1, 1),  # nothing <= 0.3 -> 0 -> clamped to min_rank 1 ; inclusive: 0.4 >= 0.3 -> 1
        (0.4, 1, 1),  # share(1) == 0.4 exactly
        (0.5, 1, 2),
        (0.7, 2, 2),  # share(2) == 0.7 exactly: both conventions agree on a tie
        (0.75, 2, 3),
        (0.9, 3, 3),
        (0.95, 3, 4),
        (0.99, 3, 4),
    ],
)
def test_energy_rules_on_4321(beta, literal, inclusive):
    d = EnergyRule(beta)(S4321)
    assert isinstance(d, RankDecision)
    assert (d.rank, d.current_rank, d.skipped) == (literal, 4, None)
    assert math.isclose(d.retained_energy, [0.4, 0.7, 0.9, 1.0][literal - 1])
    assert InclusiveEnergyRule(beta)(S4321).rank == inclusive


def test_literal_ratchets_down_for_every_beta_below_one():
    flat = torch.ones(8)
    for beta in (0.875, 0.9, 0.98, 0.999999, 1 - 1e-15):
        assert EnergyRule(beta)(flat).rank == 7, beta  # a perfectly flat spectrum still loses one
    for beta in (0.01, 0.5, 0.9, 0.98, 0.999999, 1 - 1e-15):
        assert EnergyRule(beta)(S4321).rank < 4
    # repeated events walk a healthy spectrum all the way down to min_rank
    rank, rule = 8, EnergyRule(0.98)
    history = []
    while True:
        d = rule(flat[:rank], rank, min_rank=3)
        history.append(d.rank)
        if d.rank == rank:
            break
        rank = d.rank
    assert history == [7, 6, 5, 4, 3, 3]


def test_inclusive_keeps_a_flat_spectrum():
    flat = torch.ones(8)
    assert InclusiveEnergyRule(0.98)(flat).rank == 8
    assert InclusiveEnergyRule(0.9)(flat).rank == 8  # share(7) = 0.875 < 0.9
    assert InclusiveEnergyRule(0.85)(flat).rank == 7


def test_literal_returns_zero_clamped_to_min_rank():
    s = t([10.0, 0.1, 0.1])  # share(1) = 0.98... > 0.5: literal Eq. 10 gives 0
    assert EnergyRule(0.5)(s).rank == 1
    assert EnergyRule(0.5)(s, min_rank=2).rank == 2
    assert EnergyRule(0.5)(t([3.0])).rank == 1  # a rank-1 layer: Eq. 10 gives 0, clamp keeps 1


def test_min_rank_above_current_keeps_current():
    for rule in (EnergyRule(0.5), InclusiveEnergyRule(0.5), RatioRule(0.5), FixedRank(1)):
        d = rule(S4321, current_rank=4, min_rank=10)
        assert d.rank == 4 and d.skipped is None, rule


def test_rules_never_exceed_current_rank():
    # the spectrum of the dense matrix may be longer than the layer's current rank
    s = torch.ones(10)
    assert InclusiveEnergyRule(0.98)(s, current_rank=4).rank == 4
    assert RatioRule(0.5)(s, current_rank=4).rank == 4
    assert FixedRank(9)(s, current_rank=4).rank == 4


def test_unsorted_spectrum_is_sorted_first():
    s = t([1.0, 4.0, 2.0, 3.0])
    assert EnergyRule(0.75)(s).rank == 2
    assert InclusiveEnergyRule(0.75)(s).rank == 3
    assert RatioRule(0.6)(s).rank == 3


def test_decimal_beta_is_scale_invariant():
    # share(7) of a flat 10-spectrum is 7/10 exactly; as beta=0.7 is meant: a tie, whatever the scale.
    # In float64 the cumsum of 0.1s gives 0.7000000000000001, which must not flip the answer.
    for scale in (1.0, 0.1, 0.3, 0.7, 1 / 3, 1e-3, 1e3):
        s = torch.full((10,), scale, dtype=torch.float64)
        for k in range(1, 10):
            beta = k / 10
            assert EnergyRule(beta)(s).rank == k, (scale, beta)
            assert InclusiveEnergyRule(beta)(s).rank == k, (scale, beta)


def test_float64_decides_near_beta_one():
    # one dominant direction plus ten tiny ones: float32 loses the tiny ones in the cumsum
    vals = [1.0] + [2e-8] * 10
    beta = 0.99999995
    s64 = t(vals)
    exact = exact_shares(vals)
    lit_ref = max(l for l in range(1, 12) if exact[l - 1] <= Fraction(beta))
    inc_ref = min(l for l in range(1, 12) if exact[l - 1] >= Fraction(beta))
    assert (lit_ref, inc_ref) == (8, 9)
    # precondition: a float32 computation of the same shares gives different answers
    s32 = s64.float()
    share32 = s32.cumsum(0) / s32.sum()
    lit32 = int(torch.nonzero(share32 <= beta).flatten()[-1]) + 1
    inc32 = int(torch.nonzero(share32 >= beta).flatten()[0]) + 1 if bool((share32 >= beta).any()) else 11
    assert (lit32, inc32) != (8, 9)
    assert EnergyRule(beta)(s64).rank == 8
    assert InclusiveEnergyRule(beta)(s64).rank == 9
    # a float32 tensor is upcast before any arithmetic: same answer as float64 on the same (rounded) values
    up = s32.double()
    assert EnergyRule(beta)(s32).rank == EnergyRule(beta)(up).rank
    assert InclusiveEnergyRule(beta)(s32).rank == InclusiveEnergyRule(beta)(up).rank


def test_energy_share_helper():
    assert math.isclose(energy_share(S4321, 2), 0.7)
    assert math.isnan(energy_share(torch.zeros(3), 1))


# ---------------------------------------------------------------------------------------------------------
# Eq. 33 ratio rule, FixedRank
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "beta,expected",
    [
        (0.8, 2),  # 3/4 <= 0.8
        (0.75, 2),  # tie at 3/4
        (0.6, 3),
        (0.5, 3),  # tie at 2/4
        (0.3, 4),
        (0.2, 4),  # no value falls below 0.2 * s_1: keep the rank
    ],
)
def test_ratio_rule_eq33(beta, expected):
    d = RatioRule(beta)(S4321)
    assert d.rank == expected and d.skipped is None


def test_ratio_rule_decimal_beta_is_scale_invariant():
    # s_2 / s_1 is 0.2 exactly; after scaling by 0.1 float64 gives 0.20000000000000004, still a tie
    for scale in (1.0, 0.1, 3.0, 0.3, 1e-3):
        for k in range(1, 10):
            s = t([1.0, k / 10, k / 20]) * scale
            assert RatioRule(k / 10)(s).rank == 2, (scale, k)


def test_ratio_rule_no_value_below_keeps_rank_even_when_current_is_smaller():
    s = t([1.0, 0.99, 0.98, 0.97, 0.96])
    assert RatioRule(0.5)(s).rank == 5
    assert RatioRule(0.5)(s, current_rank=3).rank == 3


def test_ratio_rule_depends_only_on_the_top_value():
    # paper D.4: rescaling all but s_1 changes nothing as long as the threshold is not crossed
    a = t([10.0, 9.0, 8.0, 1.0])
    b = t([10.0, 6.0, 5.5, 5.1])
    assert RatioRule(0.5)(a).rank == 4 and RatioRule(0.5)(b).rank == 4


def test_fixed_rank():
    assert FixedRank(2)(S4321).rank == 2
    assert FixedRank(9)(S4321).rank == 4  # never grows
    assert FixedRank(1)(S4321, min_rank=3).rank == 3
    for bad in (0, -1, 2.0, True, None):
        with pytest.raises(AdaRLValueError, match=">= 1"):
            FixedRank(bad)


# ---------------------------------------------------------------------------------------------------------
# PolicyFitRule (upper level of Eq. 8)
# ---------------------------------------------------------------------------------------------------------


def test_policy_fit_argmin_of_fit_plus_lambda_r():
    fits = {1: 1.0, 2: 0.5, 3: 0.1, 4: 0.05, 5: 0.0, 6: 0.0}
    calls = []

    def fit(r):
        calls.append(r)
        return fits[r]

    d = PolicyFitRule(lam=0.1)(torch.ones(6), fit=fit)  # costs 1.1, 0.7, 0.4, 0.45, 0.5, 0.6
    assert d.rank == 3
    assert sorted(calls) == [1, 2, 3, 4, 5, 6]
    assert PolicyFitRule(lam=0.0)(torch.ones(6), fit=fits.get).rank == 5  # smallest of the two zeros
    assert PolicyFitRule(lam=10.0)(torch.ones(6), fit=fits.get).rank == 1
    assert PolicyFitRule(lam=0.1)(torch.ones(6), fit=fits.get, min_rank=4).rank == 4


def test_policy_fit_ties_pick_smallest_rank():
    lam = 0.25
    d = PolicyFitRule(lam=lam)(torch.ones(8), fit=lambda r: 2.0 - lam * r)  # every cost is exactly 2
    assert d.rank == 1
    assert PolicyFitRule(lam=lam)(torch.ones(8), fit=lambda r: 2.0 - lam * r, min_rank=3).rank == 3


def test_policy_fit_only_tries_ranks_in_range_and_ignores_non_finite():
    calls = []

    def fit(r):
        calls.append(r)
        return float("nan") if r == 2 else (float("inf") if r == 3 else 1.0 / r)

    d = PolicyFitRule(lam=0.0)(torch.ones(10), current_rank=5, fit=fit, min_rank=2)
    assert min(calls) == 2 and max(calls) == 5
    assert d.rank == 5  # 2 and 3 are ignored; 1/r decreases
    # all non-finite: keep the current rank
    assert PolicyFitRule()(torch.ones(4), fit=lambda r: float("nan")).rank == 4


def test_policy_fit_candidate_thinning():
    calls = []

    def fit(r):
        calls.append(r)
        return abs(r - 37) / 10

    d = PolicyFitRule(lam=0.0, candidates=5)(torch.ones(200), fit=fit)
    assert len(calls) <= 5 and len(set(calls)) == len(calls)
    assert 1 in calls and 200 in calls
    assert calls == sorted(calls)
    assert d.rank == min(calls, key=lambda r: (abs(r - 37), r))
    # with enough candidates every rank is tried
    calls.clear()
    PolicyFitRule(lam=0.0, candidates=64)(torch.ones(30), fit=fit)
    assert calls == list(range(1, 31))


def test_policy_fit_needs_fit_and_validates():
    with pytest.raises(AdaRLValueError, match="fit"):
        PolicyFitRule()(torch.ones(4))
    for lam in (-1.0, float("inf"), float("nan"), True, "0.1"):
        with pytest.raises(AdaRLValueError, match="lam"):
            PolicyFitRule(lam=lam)
    for c in (1, 0, 2.5, True):
        with pytest.raises(AdaRLValueError, match="candidates"):
            PolicyFitRule(candidates=c)


# ---------------------------------------------------------------------------------------------------------
# skip behaviour, validation, registry
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "spectrum,reason",
    [
        ([4.0, float("nan"), 1.0], "non-finite"),
        ([float("inf"), 1.0, 1.0], "non-finite"),
        ([0.0, 0.0, 0.0], "zero"),
        ([1e-13, 1e-14, 0.0], "zero"),
        ([], "empty"),
    ],
)
def test_skip_keeps_current_rank_with_reason(spectrum, reason):
    called = []
    rules = [EnergyRule(0.5), InclusiveEnergyRule(0.5), RatioRule(0.5), FixedRank(1), PolicyFitRule()]
    for rule in rules:
        d = rule(t(spectrum), current_rank=3, fit=lambda r: called.append(r) or 0.0)
        assert d.rank == 3 and d.current_rank == 3, rule
        assert d.skipped is not None and reason in d.skipped, (rule, d.skipped)
        assert math.isnan(d.retained_energy)
    assert called == []  # a skipped event never evaluates the fit
    assert EnergyRule(0.5)(S4321).as_dict()["skipped"] is None


@pytest.mark.parametrize("cls", [EnergyRule, InclusiveEnergyRule, RatioRule])
@pytest.mark.parametrize("beta", [0, 1, 1.0, 1.5, -0.1, float("nan"), float("inf"), True, False, "0.5", None])
def test_invalid_beta_raises_with_allowed_range(cls, beta):
    with pytest.raises(AdaRLValueError, match=r"\(0, 1\)"):
        cls(beta)


def test_invalid_current_and_min_rank():
    with pytest.raises(AdaRLValueError, match="current_rank"):
        EnergyRule(0.9)(S4321, current_rank=0)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(AdaRLValueError, match="min_rank"):
            EnergyRule(0.9)(S4321, min_rank=bad)


def test_make_rule():
    assert set(plugins.BUILTIN_RANK_RULES) == {"energy", "energy_inclusive", "ratio", "fixed", "policy_fit"}
    r = make_rule("energy", beta=0.9)
    assert type(r) is EnergyRule and r.beta == 0.9
    assert type(make_rule("energy_inclusive")) is InclusiveEnergyRule
    assert type(make_rule("ratio", beta=0.5)) is RatioRule
    assert make_rule("fixed", target_rank=3).target_rank == 3
    assert make_rule("policy_fit", lam=0.5).lam == 0.5
    assert "beta=0.9" in repr(r)
    with pytest.raises(AdaRLValueError) as err:
        make_rule("svd_energy")
    for name in plugins.BUILTIN_RANK_RULES:
        assert repr(name) in str(err.value)
    with pytest.raises(AdaRLValueError, match="energy"):
        make_rule("energy", gamma=0.5)
    with pytest.raises(AdaRLValueError, match="fixed"):
        make_rule("fixed")  # missing target_rank


# ---------------------------------------------------------------------------------------------------------
# properties (hypothesis), against exact arithmetic
# ---------------------------------------------------------------------------------------------------------

TOL = 1e-9  # the rules resolve ties within ~1e-12; hypothesis values closer than this to a share are ties

spectra = st.lists(
    st.floats(min_value=1e-6, max_value=1e3, allow_nan=False, allow_infinity=False), min_size=1, max_size=24
)
betas = st.floats(min_value=1e-3, max_value=1 - 1e-6)


@settings(max_examples=300, deadline=None)
@given(spectra, betas)
def test_property_literal_is_largest_share_at_most_beta(values, beta):
    s = sorted(values, reverse=True)
    n = len(s)
    sh = exact_shares(s)
    b = Fraction(beta)
    r = EnergyRule(beta)(t(values)).rank
    assert 1 <= r <= max(1, n - 1)  # the ratchet: never the current rank when n >= 2
    if sh[0] > b + Fraction(TOL):
        assert r == 1  # Eq. 10 gives 0, clamped to min_rank
    else:
        assert sh[r - 1] <= b + Fraction(TOL)
        assert r == n or sh[r] > b - Fraction(TOL)


@settings(max_examples=300, deadline=None)
@given(spectra, betas)
def test_property_inclusive_is_smallest_share_at_least_beta(values, beta):
    s = sorted(values, reverse=True)
    sh = exact_shares(s)
    b = Fraction(beta)
    r = InclusiveEnergyRule(beta)(t(values)).rank
    assert 1 <= r <= len(s)
    assert sh[r - 1] >= b - Fraction(TOL)
    assert r == 1 or sh[r - 2] < b + Fraction(TOL)
    # it is the (clamped) literal answer or one more: equal on an exact tie, one more otherwise
    lit = EnergyRule(beta)(t(values)).rank
    assert r - lit in (0, 1)


@settings(max_examples=200, deadline=None)
@given(spectra, betas, st.sampled_from([1e-4, 0.1, 0.3, 7.0, 1e4]))
def test_property_scale_invariance(values, beta, scale):
    s = t(values)
    # a spectrum whose largest value is at or below zero_tol (absolute, 1e-10) is "~zero" by contract: kept as is
    assume(max(values) * min(scale, 1.0) > 1e-10)
    for rule in (EnergyRule(beta), InclusiveEnergyRule(beta), RatioRule(beta)):
        a, b = rule(s).rank, rule(s * scale).rank
        if a != b:  # only allowed when the spectrum sits (numerically) on the threshold
            sh = exact_shares(sorted(values, reverse=True))
            ratios = [Fraction(x) / Fraction(max(values)) for x in values]
            near = [abs(x - Fraction(beta)) for x in (sh + ratios)]
            assert min(near) < Fraction(TOL), (rule, a, b)


def test_fixed_rule_takes_the_recipe_key_name_only():
    """Issues 29.7 and 47: one name for one thing, ``target_rank`` in Python as in recipes (``rank.target_rank``);
    the old keyword and attribute ``rank`` are gone."""
    s = torch.tensor([5.0, 3.0, 1.0, 0.5, 0.5])
    assert make_rule("fixed", target_rank=2)(s).rank == 2
    assert FixedRank(target_rank=3).target_rank == 3 and FixedRank(4)(s).rank == 4
    with pytest.raises(TypeError, match="rank"):
        FixedRank(rank=2)
    assert not hasattr(FixedRank(2), "rank")
    with pytest.raises(AdaRLValueError, match="'fixed'.*target_rank"):
        make_rule("fixed")
