"""Every interval in every committed ``docs/reports/*/statistics.csv`` is recomputed by an estimator written apart
from ``adarl.experiments.report.stats`` (issue 45), end to end: the runs' scores are read again from the committed run
folders (``runs/<axis>=<value>__...__seed=<n>/eval.csv``) by a loader of this file, and the bootstrap is
``scipy.stats.bootstrap`` (percentile method, 95%, each arm's seeds resampled with replacement on their own) with
its own generator and ten times the resamples. Nothing of adarl is imported.

What a row of statistics.csv states, as ``adarl.experiments.report._sections`` writes it (and report.md says in words):

* a run's score is the mean of its last ``score_last`` nominal evaluations (eval.csv's ``mean`` column, file order;
  report.md: "Score of a run: its last evaluation" or "the mean of its last N evaluations");
* ``mean_pt [mean_lo, mean_hi]``: the mean of a setting's seed scores with the 2.5% and 97.5% percentiles of its
  bootstrap distribution; ``iqm [iqm_lo, iqm_hi]`` the same for the interquartile mean (rliable's: the mean of the
  sorted scores with ``floor(n/4)`` cut from each end); no interval (nan) with fewer than two seeds;
* ``poi_ref [poi_lo, poi_hi]``: P(reference > setting) = the mean over all (a, b) pairs of 1[a > b] + 0.5 1[a = b],
  a a reference seed and b a seed of the row's setting with the same other axes; both arms resampled independently
  (the stratified bootstrap of rliable: runs never cross arms); nan for the reference itself. The reference is the
  one named in report.md's "P(<ref> > setting)".

A committed end is a 2.5% (97.5%) sample quantile of the report's B = 2000 resamples (report.md: "2000
resamples"), so it is itself random; see :func:`_end_agrees` for the Monte-Carlo tolerance. Points must match to
rounding. A second test feeds tampered copies through the same checker and asserts that they are flagged.
"""

from __future__ import annotations

import csv
import math
import re
import shutil
import statistics
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats

REPORTS = Path(__file__).resolve().parents[1] / "docs" / "reports"
STATISTICS = sorted(REPORTS.glob("*/statistics.csv"))
CONFIDENCE = 0.95
MY_RESAMPLES = 20_000
# Monte-Carlo tolerance, in standard errors of the committed quantile's probability level (see _end_agrees). A
# correct end is flagged with probability 6e-6 at Z = 5 (exactly, from the order statistic's Beta distribution at
# B = 2000, whose skew makes the far side heavier than a normal's 5.7e-7), under 2e-3 over the ~290 ends checked.
Z = 5.0
ENDS = {"mean_pt": ("mean_lo", "mean_hi"), "iqm": ("iqm_lo", "iqm_hi"), "poi_ref": ("poi_lo", "poi_hi")}


# ---------------------------------------------------------------------------------- the independent estimators


def _iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """rliable's interquartile mean: sort, cut ``floor(n / 4)`` scores from each end, average the rest."""
    x = np.sort(np.asarray(x, dtype=float), axis=axis)
    n = x.shape[axis]
    cut = n // 4
    return np.take(x, np.arange(cut, n - cut), axis=axis).mean(axis=axis)


def _mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.asarray(x, dtype=float).mean(axis=axis)


def _poi(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
    """P(A > B) + P(A = B) / 2 over all pairs of a run of A and a run of B (vectorised over leading axes)."""
    a, b = np.moveaxis(np.asarray(a, float), axis, -1), np.moveaxis(np.asarray(b, float), axis, -1)
    a, b = a[..., :, None], b[..., None, :]
    return ((a > b) + 0.5 * (a == b)).mean(axis=(-2, -1))


def _bootstrap(samples: tuple[np.ndarray, ...], statistic, seed_text: str) -> np.ndarray:
    """``MY_RESAMPLES`` values of ``statistic`` on resamples drawn by scipy.stats.bootstrap: each sample (arm) with
    replacement on its own (``paired=False``), a generator seeded from the row's name (reproducible, and not the
    report's stream). Returns the bootstrap distribution; its percentile interval is what the report states."""
    res = stats.bootstrap(
        samples,
        statistic,
        n_resamples=MY_RESAMPLES,
        vectorized=True,
        paired=False,
        method="percentile",
        confidence_level=CONFIDENCE,
        rng=np.random.default_rng(zlib.crc32(seed_text.encode())),
    )
    return np.asarray(res.bootstrap_distribution, dtype=float)


def _end_agrees(committed: float, boot: np.ndarray, p: float, b_committed: int) -> tuple[bool, float]:
    """Whether ``committed``, the p-quantile of the report's ``b_committed`` bootstrap values, is a p-quantile of
    the same bootstrap distribution as ``boot`` (this file's resamples), within Monte-Carlo error; and that error's
    size in standard errors (0 inside the band).

    The check is made on the probability scale, not the score scale: with F the exact bootstrap distribution,
    F(committed) is the coverage of a sample p-quantile of B draws, p +- sqrt(p (1 - p) / B) (Beta(Bp, B(1-p))),
    plus at most 1/B from np.quantile's interpolation between neighbouring order statistics; this file estimates
    F with its own B' resamples, error sqrt(p (1 - p) / B'). So F' (this file's ECDF) at the committed end must lie
    within Z sqrt(p (1 - p) (1/B + 1/B')) + 1/B of p. No density estimate is needed, and discreteness comes for
    free: a small-sample P(A > B) (steps of 1/(n_a n_b)) or an n = 2 mean has atoms, and then F' jumps over
    [F'(c-), F'(c)], which is compared as an interval (one atom's width of slack, whatever its size). Ties between
    the two computations' float values are absorbed by a relative 1e-9."""
    eps = 1e-9 * max(1.0, abs(committed))
    below = float(np.mean(boot < committed - eps))  # F'(c-)
    upto = float(np.mean(boot <= committed + eps))  # F'(c)
    se = math.sqrt(p * (1 - p) * (1 / b_committed + 1 / boot.size))
    gap = max(below - p, p - upto, 0.0)  # distance from p to [F'(c-), F'(c)]
    gap = max(gap - 1 / b_committed, 0.0)
    return gap <= Z * se, gap / se


# ------------------------------------------------------------------------------------- the independent loader


def _report_rules(folder: Path) -> tuple[int, str | None, int]:
    """From report.md's words: the score rule (last N evaluations), the reference of P(ref > setting) (None: no
    probability of improvement), and the report's number of bootstrap resamples."""
    text = (folder / "report.md").read_text()
    rule = re.search(r"Score of a run: (its last evaluation|the mean of its last (\d+) evaluations)", text)
    assert rule, f"{folder.name}: report.md states no score rule"
    last = int(rule.group(2) or 1)
    ref = re.search(r"P\((\S+) > setting\)", text)
    reps = re.search(r"(\d+) resamples", text)
    assert reps, f"{folder.name}: report.md states no number of resamples"
    return last, ref.group(1) if ref else None, int(reps.group(1))


def _runs_folders(folder: Path) -> list[Path]:
    """Where a report's runs are: its own ``runs/``, or for an aggregate of other reports' runs (Table 1 across its
    rows, docs/reports/table1) the ``runs/`` folders its ``rows.txt`` names, relative to the repository."""
    if (folder / "rows.txt").is_file():
        return [REPORTS.parents[1] / line for line in (folder / "rows.txt").read_text().split()]
    return [folder / "runs"]


def _run_scores(folder: Path, last: int) -> dict[tuple[tuple[str, str], ...], list[float]]:
    """Per setting (the run folder's ``axis=value`` parts but the seed), one score per seed: the mean of the run's
    last ``last`` eval.csv means. The folder's seed must be its recipe's."""
    out: dict[tuple[tuple[str, str], ...], dict[int, float]] = {}
    for run in sorted(r for runs in _runs_folders(folder) for r in runs.iterdir()):
        parts = [p.partition("=") for p in run.name.split("__")]
        assert parts[-1][0] == "seed" and all(sep for _, sep, _ in parts), f"{run}: not an <axis>=<value> name"
        seed = int(parts[-1][2])
        assert int(yaml.safe_load((run / "recipe.yaml").read_text())["seed"]) == seed, run
        with (run / "eval.csv").open(newline="") as fh:
            means = [float(r["mean"]) for r in csv.DictReader(fh)]
        assert means, f"{run}: no evaluation"
        key = tuple((k, v) for k, _, v in parts[:-1])
        assert seed not in out.setdefault(key, {}), f"{run}: seed {seed} twice"
        out[key][seed] = statistics.fmean(means[-last:])
    return {k: list(v.values()) for k, v in out.items()}


def _read_statistics(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    header = list(rows[0]) if rows else []
    return header[: header.index("n_seeds")], rows


def _f(s: str) -> float:
    return float(s) if s not in ("", "nan") else math.nan


def check_statistics(folder: Path, statistics_csv: Path | None = None) -> tuple[list[str], list[dict]]:
    """Recompute every point and interval of ``statistics_csv`` (default: the folder's own) from ``folder``'s runs.
    Returns the disagreements (empty: all agree) and one record per interval end checked."""
    statistics_csv = statistics_csv or folder / "statistics.csv"
    last, ref, b_committed = _report_rules(folder)
    scores = _run_scores(folder, last)
    axes, rows = _read_statistics(statistics_csv)
    problems: list[str] = []
    checked: list[dict] = []
    keys = [tuple((a, r[a]) for a in axes) for r in rows]
    assert sorted(keys) == sorted(scores), f"{folder.name}: statistics.csv's settings are not its runs'"
    col = None
    if ref is not None:
        (col,) = {a for k in keys for a, v in k if v == ref}  # the column axis holds the reference
    for row, key in zip(rows, keys):
        name = f"{folder.name}: {dict(key)}"
        x = np.asarray(scores[key])
        if "score_last" in row and row["score_last"]:
            assert int(row["score_last"]) == last, f"{name}: score_last against report.md's rule"
        if int(row["n_seeds"]) != x.size:
            problems.append(f"{name}: n_seeds {row['n_seeds']}, the runs have {x.size}")
            continue
        todo = {"mean_pt": ((x,), _mean), "iqm": ((x,), _iqm)}
        if col is not None and dict(key)[col] != ref:
            partner = tuple((a, ref if a == col else v) for a, v in key)
            if partner in scores:
                todo["poi_ref"] = ((np.asarray(scores[partner]), x), _poi)
        for point_col, (samples, statistic) in todo.items():
            point = float(statistic(*samples))
            if not math.isclose(_f(row[point_col]), point, rel_tol=1e-9, abs_tol=1e-12):
                problems.append(f"{name}: {point_col} {row[point_col]}, recomputed {point!r}")
            lo_col, hi_col = ENDS[point_col]
            if min(s.size for s in samples) < 2 and point_col != "poi_ref":  # no interval from one seed
                if not (math.isnan(_f(row[lo_col])) and math.isnan(_f(row[hi_col]))):
                    problems.append(f"{name}: {lo_col} and {hi_col} give an interval from {x.size} seed")
                continue
            if min(s.size for s in samples) < 2:  # P against one seed: that seed resamples to itself, the other arm
                (one,), other = [s for s in samples if s.size < 2], [s for s in samples if s.size >= 2]
                if not other:  # one seed a side: every resample is the point
                    samples, statistic = (
                        (np.repeat(samples[0], 2),),
                        (lambda y, p=point, axis=-1: np.full(y.shape[:-1], p)),
                    )
                elif samples[0].size < 2:
                    samples, statistic = (
                        (other[0],),
                        (lambda y, a=one, axis=-1: _poi(np.full(y.shape[:-1] + (1,), a), y)),
                    )
                else:
                    samples, statistic = (
                        (other[0],),
                        (lambda y, b=one, axis=-1: _poi(y, np.full(y.shape[:-1] + (1,), b))),
                    )
            boot = _bootstrap(samples, statistic, f"{name} {point_col}")
            alpha = (1 - CONFIDENCE) / 2
            mine = np.quantile(boot, [alpha, 1 - alpha])
            for end_col, p, my_end in zip((lo_col, hi_col), (alpha, 1 - alpha), mine):
                committed = _f(row[end_col])
                ok, z = (False, math.inf) if math.isnan(committed) else _end_agrees(committed, boot, p, b_committed)
                checked.append(
                    {"row": name, "column": end_col, "committed": committed, "recomputed": float(my_end), "z": z}
                )
                if not ok:
                    problems.append(f"{name}: {end_col} {committed!r}, recomputed {my_end!r} ({z:.1f} standard errors)")
        for point_col in set(ENDS) - set(todo):  # nothing to estimate: the reference itself, or no partner
            if any(not math.isnan(_f(row[c])) for c in (point_col, *ENDS[point_col]) if c in row):
                problems.append(f"{name}: {point_col} has values with nothing to compare")
    return problems, checked


# ------------------------------------------------------------------------------------------------------ tests


def test_every_committed_statistics_csv_has_its_runs():
    """The check covers every statistics.csv under docs/reports (a report committed without its runs, or a new
    report's interval, cannot escape it); an aggregate of other reports' runs names them in rows.txt."""
    assert len(STATISTICS) >= 17
    for path in STATISTICS:
        runs = _runs_folders(path.parent)
        assert runs and all(r.is_dir() for r in runs) and (path.parent / "report.md").is_file(), path.parent


@pytest.mark.parametrize("report", [p.parent.name for p in STATISTICS])
def test_statistics_csv_intervals_recomputed_independently(report):
    problems, _ = check_statistics(REPORTS / report)
    assert not problems, "\n".join(problems)


def test_a_tampered_statistics_csv_is_flagged(tmp_path):
    """The check can fail: copies of table1-pilot's statistics.csv (never the committed file), each with one row
    changed, are flagged at exactly the values changed; the untouched copy passes.

    Its resolution is the committed bootstrap's own: with 2000 resamples a 97.5% end is uncertain by about +-0.0035
    in probability, i.e. several steps of a small P(A > B) (sac_full's poi_hi 0.4375 -> 0.5, 8 x 8 seeds, is 2.6
    standard errors and passes; a 90% interval stated as 95% is 5-7 on a mean of 8 seeds, at the edge), so the
    tampering below is of the size a real mistake makes: a wrong point, an end outside the bootstrap's support,
    another row's interval, an 80% interval stated as 95%."""
    folder = REPORTS / "table1-pilot"
    copy = tmp_path / "table1-pilot"
    copy.mkdir()
    (copy / "runs").symlink_to(folder / "runs", target_is_directory=True)
    shutil.copy(folder / "report.md", copy / "report.md")
    with (folder / "statistics.csv").open(newline="") as fh:
        header, *rows = list(csv.reader(fh))
    at = {name: i for i, name in enumerate(header)}
    original = {r[at["algorithm"]]: dict(zip(header, r)) for r in rows}

    def flagged(algorithm: str, changes: dict[str, str]) -> list[str]:
        changed = [list(r) for r in rows]
        (row,) = [r for r in changed if r[at["algorithm"]] == algorithm]
        for column, value in changes.items():
            row[at[column]] = value
        with (copy / "statistics.csv").open("w", newline="") as fh:
            csv.writer(fh).writerows([header, *changed])
        return check_statistics(copy)[0]

    assert flagged("adarl", {}) == []  # the untouched copy passes
    parseval = np.asarray(_run_scores(folder, 3)[(("env", "hopper"), ("algorithm", "parseval"))])
    eighty = np.quantile(_bootstrap((parseval,), _mean, "another stream"), [0.10, 0.90])
    tamper = [
        ("fixed_final", {"poi_ref": "0.25"}),  # 0.2 -> 0.25: the point off by two pairs in forty
        ("sac_full", {"poi_hi": "0.7"}),  # 0.4375 -> 0.7: adarl's "beats" verdict turned into "no difference"
        ("adarl", {"iqm_lo": original["parseval"]["iqm_lo"], "iqm_hi": original["parseval"]["iqm_hi"]}),  # rows mixed
        ("parseval", {"mean_lo": str(float(eighty[0])), "mean_hi": str(float(eighty[1]))}),  # 80%, not 95%
    ]
    for algorithm, changes in tamper:
        problems = flagged(algorithm, changes)
        assert all(f"'algorithm': '{algorithm}'" in p for p in problems), problems
        assert sorted(p.split("}: ", 1)[1].split(" ")[0] for p in problems) == sorted(changes), problems
