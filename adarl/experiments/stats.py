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
  task (ties count half; the Mann-Whitney U statistic over ``n m``), averaged over tasks.

With five seeds the intervals are wide, and they should be: they say how little five seeds pin down.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import stats as _st

__all__ = ["iqm", "stratified_bootstrap", "probability_of_improvement", "interval_estimate", "poi_estimate"]

REPS = 2000
CONFIDENCE = 0.95


def iqm(scores: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean: the mean of the scores between the 25th and 75th percentiles (rliable's definition)."""
    x = np.asarray(scores, dtype=float).ravel()
    if x.size == 0:
        return float("nan")
    return float(_st.trim_mean(x, 0.25))


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


def interval_estimate(
    scores, statistic: str = "iqm", *, reps: int = REPS, confidence: float = CONFIDENCE, seed: int = 0
) -> tuple[float, float, float]:
    """``(point, low, high)`` of the IQM (or ``"mean"``) of the runs' scores, pooled over tasks, with a stratified
    bootstrap percentile interval. ``scores``: a flat list (one task) or a list of per-task lists. The resamples are
    :func:`stratified_bootstrap`'s (same seed, same draws), the statistic computed on all of them at once."""
    tasks = [t for t in _tasks(scores) if t.size]
    if not tasks:
        return (float("nan"),) * 3
    if statistic not in ("iqm", "mean"):
        raise ValueError(f"statistic must be 'iqm' or 'mean', got {statistic!r}")
    pooled = np.concatenate(tasks)
    point = iqm(pooled) if statistic == "iqm" else float(np.mean(pooled))
    if pooled.size < 2:
        return point, float("nan"), float("nan")
    idx = _resample_indices([t.size for t in tasks], reps, np.random.default_rng(seed))
    resamples = np.concatenate([t[i] for t, i in zip(tasks, idx)], axis=1)  # (reps, runs), tasks side by side
    boot = _st.trim_mean(resamples, 0.25, axis=1) if statistic == "iqm" else np.mean(resamples, axis=1)
    a = (1 - confidence) / 2
    return point, float(np.quantile(boot, a)), float(np.quantile(boot, 1 - a))


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
