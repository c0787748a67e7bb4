"""Statistics a careful reader of an RL table trusts: IQM, stratified bootstrap intervals, probability of improvement.

The estimators of Agarwal et al. (2021), "Deep RL at the edge of the statistical precipice", as the ``rliable``
library computes them, written with numpy and scipy. Why not ``rliable`` itself: version 1.2.0 needs ``arch<8``,
and ``arch`` 7.2 fails to import with the pandas 3 this project pins (``deprecate_kwarg`` changed signature), so
``import rliable`` raises. The formulas are short:

* **IQM**: the mean of the middle 50% of the scores (``scipy.stats.trim_mean(x, 0.25)``), robust to one outlying
  seed and more efficient than the median;
* **stratified bootstrap**: runs are resampled with replacement *within each task* (env), never across, and the
  statistic is recomputed on each resample; the interval is the percentile interval of the resamples (rliable's
  default), 2000 resamples, a fixed seed so that a report is reproducible;
* **probability of improvement** ``P(X > Y)``: the chance that a run of X scores above a run of Y on the same
  task (ties count half; the Mann-Whitney U statistic over ``n m``), averaged over tasks;
* **optimality gap** at a threshold ``gamma``: how far the runs fall short of it on average,
  ``gamma - mean(min(x, gamma))`` (rliable's ``aggregate_optimality_gap``; on normalised scores, ``gamma = 1``);
* **performance profile**: the share of runs whose score exceeds each threshold ``tau`` (rliable's score
  distribution), with a stratified-bootstrap band per ``tau``.

Across tasks (envs) the runs' scores are pooled, as rliable pools a runs x tasks matrix (with the same number of
runs per task, each task weighs the same).

With five seeds the intervals are wide, and they should be: they say how little five seeds pin down.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import stats as _st

__all__ = [
    "iqm",
    "optimality_gap",
    "stratified_bootstrap",
    "probability_of_improvement",
    "interval_estimate",
    "poi_estimate",
    "performance_profile",
]

REPS = 2000
CONFIDENCE = 0.95


def iqm(scores: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean: the mean of the scores between the 25th and 75th percentiles (rliable's definition)."""
    x = np.asarray(scores, dtype=float).ravel()
    if x.size == 0:
        return float("nan")
    return float(_st.trim_mean(x, 0.25))


def optimality_gap(scores: Sequence[float] | np.ndarray, gamma: float = 1.0) -> float:
    """How far the scores fall short of ``gamma`` on average: ``gamma - mean(min(x, gamma))`` (rliable's definition;
    0 when every score reaches ``gamma``; a score above it does not make up for one below)."""
    x = np.asarray(scores, dtype=float).ravel()
    if x.size == 0:
        return float("nan")
    return float(gamma - np.mean(np.minimum(x, gamma)))


def _tasks(scores) -> list[np.ndarray]:
    """One array of run scores per task: a flat sequence is one task."""
    if len(scores) and np.ndim(scores[0]) == 0:
        return [np.asarray(scores, dtype=float)]
    return [np.asarray(t, dtype=float).ravel() for t in scores]


def stratified_bootstrap(
    tasks: Sequence[np.ndarray], statistic: Callable[[list[np.ndarray]], float], *, reps: int = REPS, seed: int = 0
) -> np.ndarray:
    """``reps`` values of ``statistic`` on resamples that draw each task's runs with replacement within the task."""
    idx = _resample_indices([len(t) for t in tasks], reps, np.random.default_rng(seed))
    return np.array([statistic([t[i[r]] for t, i in zip(tasks, idx)]) for r in range(reps)], dtype=float)


def _resample_indices(sizes: Sequence[int], reps: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Per task, a ``(reps, n)`` array of the indices :func:`stratified_bootstrap` draws (per resample, each task in
    order: the same generator calls), so that a statistic can be computed on every resample at once."""
    out = [np.empty((reps, n), dtype=np.int64) for n in sizes]
    for i in range(reps):
        for k, n in enumerate(sizes):
            out[k][i] = rng.integers(0, n, n)
    return out


_STATISTICS = ("iqm", "mean", "optimality_gap")


def interval_estimate(
    scores,
    statistic: str = "iqm",
    *,
    reps: int = REPS,
    confidence: float = CONFIDENCE,
    seed: int = 0,
    gamma: float = 1.0,
) -> tuple[float, float, float]:
    """``(point, low, high)`` of the IQM (or ``"mean"``, or ``"optimality_gap"`` at ``gamma``) of the runs' scores,
    pooled over tasks, with a stratified bootstrap percentile interval. ``scores``: a flat list (one task) or a list
    of per-task lists. The resamples are :func:`stratified_bootstrap`'s (same seed, same draws), the statistic
    computed on all of them at once."""
    if statistic not in _STATISTICS:
        raise ValueError(f"statistic must be one of {', '.join(map(repr, _STATISTICS))}, got {statistic!r}")
    tasks = [t for t in _tasks(scores) if t.size]
    if not tasks:
        return (float("nan"),) * 3
    pooled = np.concatenate(tasks)
    point = {"iqm": iqm, "mean": lambda x: float(np.mean(x)), "optimality_gap": lambda x: optimality_gap(x, gamma)}
    point = point[statistic](pooled)
    if pooled.size < 2:
        return point, float("nan"), float("nan")
    resamples = _pooled_resamples(tasks, reps, seed)
    if statistic == "iqm":
        boot = _st.trim_mean(resamples, 0.25, axis=1)
    elif statistic == "mean":
        boot = np.mean(resamples, axis=1)
    else:
        boot = gamma - np.mean(np.minimum(resamples, gamma), axis=1)
    a = (1 - confidence) / 2
    return point, float(np.quantile(boot, a)), float(np.quantile(boot, 1 - a))


def _pooled_resamples(tasks: list[np.ndarray], reps: int, seed: int) -> np.ndarray:
    """``(reps, runs)``: every stratified resample's runs, the tasks side by side (:func:`stratified_bootstrap`'s
    draws)."""
    idx = _resample_indices([t.size for t in tasks], reps, np.random.default_rng(seed))
    return np.concatenate([t[i] for t, i in zip(tasks, idx)], axis=1)


def performance_profile(
    scores, taus: Sequence[float], *, reps: int = REPS, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(share, low, high)``, one value per ``tau``: the share of runs (pooled over tasks) whose score exceeds
    ``tau``, with the stratified-bootstrap percentile band (rliable's performance profile). ``scores`` as in
    :func:`interval_estimate`; the band is nan with fewer than two runs."""
    t = np.asarray(taus, dtype=float).ravel()
    tasks = [x for x in _tasks(scores) if x.size]
    if not tasks:
        nan = np.full(t.shape, np.nan)
        return nan, nan.copy(), nan.copy()
    pooled = np.concatenate(tasks)
    share = np.mean(pooled[:, None] > t[None, :], axis=0)
    if pooled.size < 2:
        nan = np.full(t.shape, np.nan)
        return share, nan, nan.copy()
    resamples = _pooled_resamples(tasks, reps, seed)
    boot = np.mean(resamples[:, :, None] > t[None, None, :], axis=1)  # (reps, taus)
    a = (1 - confidence) / 2
    return share, np.quantile(boot, a, axis=0), np.quantile(boot, 1 - a, axis=0)


def probability_of_improvement(x: Sequence[float], y: Sequence[float]) -> float:
    """``P(X > Y) + P(X = Y) / 2`` for one task: the Mann-Whitney U statistic of x over y divided by ``n m``."""
    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    if x.size == 0 or y.size == 0:
        return float("nan")
    greater = (x[:, None] > y[None, :]).sum()
    ties = (x[:, None] == y[None, :]).sum()
    return float((greater + 0.5 * ties) / (x.size * y.size))


def poi_estimate(
    x, y, *, reps: int = REPS, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[float, float, float]:
    """``(point, low, high)`` of the probability that X improves on Y, averaged over tasks; both sides' runs are
    resampled within each task (stratified bootstrap, percentile interval). ``x``, ``y``: flat lists (one task) or
    per-task lists in the same task order."""
    xs, ys = _tasks(x), _tasks(y)
    if len(xs) != len(ys):
        raise ValueError(f"x and y must cover the same tasks, got {len(xs)} and {len(ys)}")
    pairs = [(a, b) for a, b in zip(xs, ys) if a.size and b.size]
    if not pairs:
        return (float("nan"),) * 3
    point = float(np.mean([probability_of_improvement(a, b) for a, b in pairs]))
    idx = _resample_indices([n for a, b in pairs for n in (a.size, b.size)], reps, np.random.default_rng(seed))
    per_pair = []
    for k, (a, b) in enumerate(pairs):  # P(X > Y) + P(X = Y) / 2 of every resample at once
        ra, rb = a[idx[2 * k]][:, :, None], b[idx[2 * k + 1]][:, None, :]
        greater, ties = (ra > rb).sum(axis=(1, 2)), (ra == rb).sum(axis=(1, 2))
        per_pair.append((greater + 0.5 * ties) / (a.size * b.size))
    boot = np.mean(np.stack(per_pair), axis=0)
    lo = (1 - confidence) / 2
    return point, float(np.quantile(boot, lo)), float(np.quantile(boot, 1 - lo))
