"""The committed reproduction reports (docs/reports/*/) re-derive from their runs: each run's score is read again
from its committed small files (eval.csv, recipe.yaml) by the report's own loader, must equal runs.csv's
``final_return``, and the per-setting n, mean, std and IQM must equal statistics.csv. A report edited by hand, a run
folder swapped, or a run left out of the statistics fails here (issue 16: "numbers can be re-derived")."""

from __future__ import annotations

import csv
import statistics
import tempfile
from pathlib import Path

import pytest

from adarl.experiments.report import collect_runs
from adarl.experiments.report.stats import iqm, probability_of_improvement

REPORTS = Path(__file__).resolve().parents[1] / "docs" / "reports"
DERIVABLE = sorted(
    d.name
    for d in REPORTS.iterdir()
    if (d / "runs.csv").is_file() and (d / "statistics.csv").is_file() and (d / "runs").is_dir()
)


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def test_the_laptop_reports_are_all_checked():
    """Every claim's laptop report is among the checked ones (a report committed without its runs would drop out)."""
    consistent = ["rank_trajectory", "table1", "table2", "warmstart_ablation", "parseval_lambda"]  # our physics
    assert {f"{name}-laptop_consistent" for name in consistent} | {"cartpole_rank_sweep-laptop"} <= set(DERIVABLE)
    protocol = ["table1-pilot", "table1-decisive", "table2-laptop", "warmstart_ablation-laptop"]  # the paper's physics
    protocol += ["rank_trajectory-laptop", "cartpole_rank_sweep-laptop_scored", "parseval_lambda-laptop"]
    assert set(protocol) <= set(DERIVABLE), set(protocol) - set(DERIVABLE)


@pytest.mark.parametrize("report", DERIVABLE)
def test_report_statistics_re_derive_from_its_committed_runs(report):
    folder = REPORTS / report
    header, rows = _rows(folder / "runs.csv")
    axes = header[1 : header.index("seed")]  # runs.csv: path, the experiment's axes, seed, ...
    # the run's score by the report's rule (issue 34: the mean of the last score_last evaluations); reports made
    # before that rule scored the last evaluation alone and have no score column
    scored = "score" in header
    col = {name: header.index(name) for name in ("seed", "final_return", *(("score", "score_last") if scored else ()))}
    committed = {r.path.name: r for r in collect_runs([folder / "runs"])[0]}  # the report's own loader
    listed = [Path(row[0]).name for row in rows]
    assert sorted(committed) == sorted(listed), f"{report}: runs/ and runs.csv name different runs"
    groups: dict[tuple, dict[int, float]] = {}
    best: dict[tuple, list[float]] = {}
    for name, row in zip(listed, rows):
        rec = committed[name]
        assert rec.final is not None, f"{report}: {name} has no nominal evaluation"
        assert rec.seed == int(row[col["seed"]]), f"{report}: {name}'s recipe has seed {rec.seed}"
        assert rec.final == pytest.approx(float(row[col["final_return"]]), rel=1e-9, abs=1e-9), name
        score = rec.score(int(row[col["score_last"]])) if scored else rec.final
        if scored:
            assert score == pytest.approx(float(row[col["score"]]), rel=1e-9, abs=1e-9), name
        seeds = groups.setdefault(tuple(row[1 : 1 + len(axes)]), {})
        assert rec.seed not in seeds, f"{report}: seed {rec.seed} counted twice in {dict(zip(axes, row[1:]))}"
        seeds[rec.seed] = score
        best.setdefault(tuple(row[1 : 1 + len(axes)]), []).append(rec.best)

    s_header, s_rows = _rows(folder / "statistics.csv")
    s_axes = s_header[: s_header.index("n_seeds")]
    assert len(s_axes) == len(axes), f"{report}: statistics.csv's settings {s_axes} against runs.csv's {axes}"
    s_col = {name: s_header.index(name) for name in ("n_seeds", "mean", "std", "iqm")}
    assert len(s_rows) == len(groups), f"{report}: {len(s_rows)} settings in statistics.csv, {len(groups)} in runs"
    for s in s_rows:
        key = tuple(s[: len(s_axes)])
        assert key in groups, f"{report}: statistics.csv's setting {key} has no runs in runs.csv"
        scores = list(groups[key].values())
        assert int(s[s_col["n_seeds"]]) == len(scores), key
        assert float(s[s_col["mean"]]) == pytest.approx(statistics.fmean(scores), rel=1e-9), key
        std = statistics.stdev(scores) if len(scores) > 1 else 0.0
        assert float(s[s_col["std"]]) == pytest.approx(std, rel=1e-9, abs=1e-9), key
        assert float(s[s_col["iqm"]]) == pytest.approx(iqm(scores), rel=1e-9), key
        if "plateau" in s_header and s[s_header.index("plateau")]:  # seeds whose best evaluation left the plateau
            threshold = float(s[s_header.index("plateau")])
            above = sum(1 for b in best[key] if b > threshold)
            assert int(s[s_header.index("above_plateau")]) == above, key
    if (folder / "pairs.csv").is_file():  # report.pairs: P(a > b) of two arms' scores, point estimate
        for pair in csv.DictReader((folder / "pairs.csv").open()):
            (col,) = [a for a in axes if a not in pair]  # the column axis: the one pairs.csv does not list
            key = {a: pair[a] for a in axes if a != col}
            a, b = ({**key, col: pair[x]} for x in ("a", "b"))
            sa, sb = (list(groups.get(tuple(k[x] for x in axes), {}).values()) for k in (a, b))
            assert (int(pair["n_a"]), int(pair["n_b"])) == (len(sa), len(sb)), pair
            if sa and sb:
                assert float(pair["poi"]) == pytest.approx(probability_of_improvement(sa, sb), rel=1e-9), pair


def test_fixed_final_takes_the_pilots_adarl_median_final_ranks():
    """Issue 34's fixed_final arm: per factorised layer, the median (rounded half up) of the final ranks of the
    pilot's 8 AdaRL seeds, re-derived from their committed ranks.json."""
    import json
    import math

    from adarl.runtime.config import load_recipe

    runs = sorted((REPORTS / "table1-pilot" / "runs").glob("env=hopper__algorithm=adarl__seed=*"))
    assert len(runs) == 8
    finals: dict[str, list[int]] = {}
    for run in runs:
        last = {}
        for event in json.loads((run / "ranks.json").read_text()):
            last.update({layer["name"]: int(layer["new_rank"]) for layer in event["layers"]})
        for name, rank in last.items():
            finals.setdefault(name, []).append(rank)
    median = {name: math.floor(statistics.median(ranks) + 0.5) for name, ranks in finals.items()}
    recipe = load_recipe("baselines/hopper_sac_fixed_final")
    assert list(recipe.network.actor.rank) == [median["actor.layer0"], median["actor.layer1"]]
    assert list(recipe.network.critic.rank) == [median["critic.layer0"], median["critic.layer1"]]
    assert not recipe.rank.enabled


def test_the_pilots_stated_verdicts_are_its_reports():
    """The verdicts README.md and docs/reproduction.md state for issue 34's pilot are the committed report's
    statistics (re-derived above from the runs), not numbers typed once and left behind."""
    stats = {r["algorithm"]: r for r in csv.DictReader((REPORTS / "table1-pilot" / "statistics.csv").open())}
    docs = {
        name: " ".join((REPORTS.parents[1] / name).read_text().split())
        for name in ("README.md", "docs/reproduction.md")
    }
    sac = stats["sac_full"]
    poi = f"{float(sac['poi_ref']):.2f} [{float(sac['poi_lo']):.2f}, {float(sac['poi_hi']):.2f}]"
    assert float(sac["poi_hi"]) < 0.5  # the rule's "sac_full beats adarl": the claim is contradicted
    for name, text in docs.items():
        assert f"P(AdaRL > SAC) = {poi}" in text or f"P(AdaRL > `sac_full`) = {poi}" in text, name
        plateau = f"{sac['above_plateau']} of {sac['n_seeds']}"
        assert plateau in text and f"{stats['adarl']['above_plateau']} of {stats['adarl']['n_seeds']}" in text, name
    restarts = stats["sac_restarts"]  # the control without truncation: beats AdaRL, no difference from SAC
    pair = next(r for r in csv.DictReader((REPORTS / "table1-pilot" / "pairs.csv").open()) if r["a"] == "sac_restarts")
    assert pair["b"] == "sac_full" and pair["verdict"] == "no difference shown" and float(restarts["poi_hi"]) < 0.5
    p_restarts = f"{float(restarts['poi_ref']):.2f} [{float(restarts['poi_lo']):.2f}, {float(restarts['poi_hi']):.2f}]"
    p_pair = f"{float(pair['poi']):.2f} [{float(pair['poi_lo']):.2f}, {float(pair['poi_hi']):.2f}]"
    assert f"P(AdaRL > restarts) = {p_restarts}" in docs["README.md"]
    assert f"P(AdaRL > `sac_restarts`) = {p_restarts}" in docs["docs/reproduction.md"]
    assert f"P(`sac_restarts` > `sac_full`) = {p_pair}" in docs["docs/reproduction.md"]
    assert f"{restarts['above_plateau']} of {restarts['n_seeds']} of its seeds leave" in docs["docs/reproduction.md"]
    fixed = stats["fixed_final"]  # adapting against fixing at AdaRL's final ranks: the interval reaches 0.5
    assert int(fixed["n_seeds"]) == 5 and float(fixed["poi_lo"]) <= 0.5 <= float(fixed["poi_hi"])
    p_fixed = f"{float(fixed['poi_ref']):.2f} [{float(fixed['poi_lo']):.2f}, {float(fixed['poi_hi']):.2f}]"
    assert f"P(AdaRL > `fixed_final`) = {p_fixed}" in docs["docs/reproduction.md"]
    assert f"P(AdaRL > fixed ranks) = {p_fixed}" in docs["README.md"]
    assert f"{fixed['above_plateau']} of {fixed['n_seeds']} of its seeds leave" in docs["docs/reproduction.md"]
    parseval = stats["parseval"]  # Parseval (lambda 1e-5) beats AdaRL: Table 1's claim against it contradicted
    assert int(parseval["n_seeds"]) == 5 and float(parseval["poi_hi"]) < 0.5
    p_parseval = f"{float(parseval['poi_ref']):.2f} [{float(parseval['poi_lo']):.2f}, {float(parseval['poi_hi']):.2f}]"
    assert f"P(AdaRL > `parseval`) = {p_parseval}" in docs["docs/reproduction.md"]
    assert f"P(AdaRL > Parseval) = {p_parseval}" in docs["README.md"]
    assert f"{parseval['above_plateau']} of {parseval['n_seeds']} of its seeds leave" in docs["docs/reproduction.md"]
    table = docs["docs/reproduction.md"]  # the verdict table of "Where the runs stand": the same numbers
    for arm, p in (("sac_full", poi), ("parseval", p_parseval), ("fixed_final", p_fixed)):
        row = stats[arm]
        assert f"| `adarl` {stats['adarl']['n_seeds']}, `{arm}` {row['n_seeds']} | {p} |" in table, arm
    per_seed = {}  # each arm's scores in seed order, as the docs list them
    for row in sorted(csv.DictReader((REPORTS / "table1-pilot" / "runs.csv").open()), key=lambda r: int(r["seed"])):
        per_seed.setdefault(row["algorithm"], []).append(f"{float(row['score']):.0f}")
    text = docs["docs/reproduction.md"]
    assert f"Per seed, AdaRL {', '.join(per_seed['adarl'])}; `sac_full` {', '.join(per_seed['sac_full'])}" in text
    for arm in ("sac_restarts", "fixed_final", "parseval"):
        assert f"per seed {', '.join(per_seed[arm])}" in text, arm
    for arm in ("adarl", "sac_full", "sac_restarts", "fixed_final", "parseval"):
        row = stats[arm]
        assert (
            f"{float(row['mean']):.0f} ± {float(row['std']):.0f} (IQM {float(row['iqm']):.0f})"
            in docs["docs/reproduction.md"]
        ), arm


def _poi_text(p: str, lo: str, hi: str) -> str:
    return f"{float(p):.2f} [{float(lo):.2f}, {float(hi):.2f}]"


def _stated_arm(arm: str, n_seeds: int, text: str) -> dict:
    """An amendment arm's statistics row of the pilot's report, after checking what docs/reproduction.md (``text``)
    states of it: mean ± std (IQM), the plateau count and every seed's score in seed order."""
    pilot = REPORTS / "table1-pilot"
    row = next(r for r in csv.DictReader((pilot / "statistics.csv").open()) if r["algorithm"] == arm)
    assert int(row["n_seeds"]) == n_seeds, arm
    assert f"{float(row['mean']):.0f} ± {float(row['std']):.0f} (IQM {float(row['iqm']):.0f})" in text, arm
    assert f"{row['above_plateau']} of {row['n_seeds']} of its seeds leave" in text, arm
    scores = sorted(
        (int(r["seed"]), f"{float(r['score']):.0f}")
        for r in csv.DictReader((pilot / "runs.csv").open())
        if r["algorithm"] == arm
    )
    assert f"per seed {', '.join(v for _, v in scores)}" in text, arm
    return row


def test_eq10_alones_stated_results_are_its_reports():
    """The first amendment's arm (AdaRL with Eq. 10 alone): the score, P against AdaRL and each control, and its
    ranks as docs/reproduction.md (and README.md) state them are the committed report's."""
    import json

    pilot = REPORTS / "table1-pilot"
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    eq10 = _stated_arm("adarl_eq10", 5, text)
    p_ref = _poi_text(eq10["poi_ref"], eq10["poi_lo"], eq10["poi_hi"])
    assert float(eq10["poi_lo"]) <= 0.5 <= float(eq10["poi_hi"])  # no difference shown against AdaRL
    assert f"P(AdaRL > `adarl_eq10`) = {p_ref}" in text and f"P(AdaRL > Eq. 10 alone) = {p_ref}" in readme
    pairs = [r for r in csv.DictReader((pilot / "pairs.csv").open()) if r["a"] == "adarl_eq10"]
    assert {r["b"] for r in pairs} == {"sac_full", "sac_restarts", "fixed_final", "parseval"}
    for r in pairs:  # every control beats it
        assert r["verdict"] == f"{r['b']} beats adarl_eq10" and float(r["poi_hi"]) < 0.5
        assert f"P(`adarl_eq10` > `{r['b']}`) = {_poi_text(r['poi'], r['poi_lo'], r['poi_hi'])}" in text
    # Fig. 4 without the acceptance step: the first cut of the actor's input layer is 7 in every seed, each later
    # event cuts again, nothing is unchanged over the last event
    rows = [r for r in csv.DictReader((pilot / "rank_settling.csv").open()) if r["algorithm"] == "adarl_eq10"]
    assert len(rows) == 20 and all(int(r["events_after_last_change"]) == 0 for r in rows)
    assert "no layer is unchanged over the last event in any seed" in text
    where = ("actor layer 0", "actor layer 1", "critic layer 0", "critic layer 1")
    layers = ("actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1")
    medians = [f"{statistics.median(int(r['final_rank']) for r in rows if r['layer'] == k):g}" for k in layers]
    stated = ", ".join(f"{m} ({w})" for m, w in list(zip(medians, where))[:-1])
    assert f"median final ranks are {stated} and {medians[-1]} ({where[-1]})" in text
    paths = {}
    for run in sorted(pilot.glob("runs/env=hopper__algorithm=adarl_eq10__seed=*")):
        events = json.loads((run / "ranks.json").read_text())
        paths[run.name] = [
            next(lay["new_rank"] for lay in e["layers"] if lay["name"] == "actor.layer0") for e in events
        ]
    assert len(paths) == 5 and all(p[0] == 7 for p in paths.values())
    common = [11, *max(paths.values(), key=list(paths.values()).count)]
    assert " → ".join(map(str, common)) in text


def test_factorised_restarts_stated_results_are_its_reports():
    """The second amendment's arm (AdaRL's factorised layers with its restarts, never truncated): the truncation
    alone, P(AdaRL > factorised_restarts), and the factorisation alone, P(factorised_restarts > sac_restarts), as
    docs/reproduction.md and README.md state them, are the committed report's."""
    pilot = REPORTS / "table1-pilot"
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    arm = _stated_arm("factorised_restarts", 5, text)
    p_trunc = _poi_text(arm["poi_ref"], arm["poi_lo"], arm["poi_hi"])
    assert f"P(AdaRL > `factorised_restarts`) = {p_trunc}" in text and f"P(AdaRL > never cut) = {p_trunc}" in readme
    (pair,) = [r for r in csv.DictReader((pilot / "pairs.csv").open()) if r["a"] == "factorised_restarts"]
    assert pair["b"] == "sac_restarts" and (pair["n_a"], pair["n_b"]) == ("5", "8")
    p_fact = _poi_text(pair["poi"], pair["poi_lo"], pair["poi_hi"])
    # as stated: the truncation alone shows no difference, dense SAC with the same restarts beats the factorised nets
    assert float(arm["poi_lo"]) <= 0.5 <= float(arm["poi_hi"])
    assert pair["verdict"] == "sac_restarts beats factorised_restarts" and float(pair["poi_hi"]) < 0.5
    assert f"P(`factorised_restarts` > `sac_restarts`) = {p_fact}" in text
    assert f"P(never cut > dense with restarts) = {p_fact}" in readme


def test_stage_twos_control_is_the_pilots_strongest():
    """The protocol's rule: stage 2 runs AdaRL against the control arm with the highest mean pilot score; the
    recorded selection and the decisive spec it wrote agree with the committed report's means."""
    import json

    import yaml

    stats = {r["algorithm"]: r for r in csv.DictReader((REPORTS / "table1-pilot" / "statistics.csv").open())}
    controls = ("sac_full", "sac_restarts", "fixed_final", "parseval")
    means = {arm: float(stats[arm]["mean"]) for arm in controls}
    best = max(means, key=means.get)
    record = json.loads((REPORTS / "issue34" / "strongest_control.json").read_text())
    assert record["strongest"] == best
    assert record["mean_scores"] == pytest.approx(means, rel=1e-9)
    spec = yaml.safe_load((REPORTS / "issue34" / "table1_decisive.yaml").read_text())
    assert spec["budgets"]["decisive"]["axes"]["algorithm"] == ["adarl", best]
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    ranked = sorted(controls, key=means.get, reverse=True)
    assert "Mean pilot scores of the four controls" in text
    assert ", ".join(f"`{arm}` {means[arm]:.0f}" for arm in ranked) in text


def test_stage_twos_landed_runs_are_stated_as_its_report_has_them():
    """docs/reproduction.md's stage-2 runs "as they land" (seeds, scores, best evaluations, final ranks) are the
    committed report's rows; runs that landed after the text was written may be in the report, not the reverse."""
    import json
    import re

    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    found = re.search(
        r"Stage 2, as its runs land \((\d+) of 16;.*?AdaRL seeds ([\d, and]+) are in .*?scores ([\d, and]+) \(mean "
        r".*?best evaluations ([\d, and]+), .*?final ranks actor (.+?), critic (.+?) \(",
        text,
    )
    assert found, "the stage-2 paragraph is not where the test looks for it"
    numbers = [[int(x) for x in re.findall(r"\d+", found.group(i))] for i in (2, 3, 4)]
    seeds, scores, best = numbers
    assert len(scores) == len(best) == len(seeds)
    rows = {
        int(r["seed"]): r
        for r in csv.DictReader((REPORTS / "table1-decisive" / "runs.csv").open())
        if r["algorithm"] == "adarl"
    }
    assert set(seeds) <= set(rows)
    assert [f"{float(rows[s]['score']):.0f}" for s in seeds] == [str(x) for x in scores]
    assert [f"{float(rows[s]['best_eval']):.0f}" for s in seeds] == [str(x) for x in best]
    ranks = []
    for s in seeds:
        summary = json.loads(
            (
                REPORTS / "table1-decisive" / "runs" / f"env=hopper__algorithm=adarl__seed={s}" / "summary.json"
            ).read_text()
        )
        named = {summary["layer_names"][k]: v for k, v in summary["ranks"].items()}
        ranks.append(
            (
                f"[{named['actor.layer0']}, {named['actor.layer1']}]",
                f"[{named['critic.layer0']}, {named['critic.layer1']}]",
            )
        )
    assert re.findall(r"\[\d+, \d+\]", found.group(5)) == [r[0] for r in ranks], found.group(5)
    assert re.findall(r"\[\d+, \d+\]", found.group(6)) == [r[1] for r in ranks], found.group(6)
    # Parseval's seeds as they land: the count in the heading is both arms' runs
    control = re.search(
        r"Parseval seeds ([\d, and]+) are in: scores ([\d, and]+), best evaluations ([\d, and]+) ", found.string
    )
    if control is None:
        assert int(found.group(1)) == len(seeds)
        return
    p_seeds, p_scores, p_best = ([int(x) for x in re.findall(r"\d+", control.group(i))] for i in (1, 2, 3))
    assert int(found.group(1)) == len(seeds) + len(p_seeds) and len(p_scores) == len(p_best) == len(p_seeds)
    rows = {
        int(r["seed"]): r
        for r in csv.DictReader((REPORTS / "table1-decisive" / "runs.csv").open())
        if r["algorithm"] == "parseval"
    }
    assert [f"{float(rows[s]['score']):.0f}" for s in p_seeds] == [str(x) for x in p_scores]
    assert [f"{float(rows[s]['best_eval']):.0f}" for s in p_seeds] == [str(x) for x in p_best]


#: the decisive stage's cell in the verdict table's stage column
DECISIVE = "2 (1e6: 28.6%)"


def _by_the_rule(stats_row: dict) -> tuple[str, str]:
    """A report row's P(AdaRL > arm) as the docs print it, and the verdict the pre-registered rule gives it."""
    p = _poi_text(stats_row["poi_ref"], stats_row["poi_lo"], stats_row["poi_hi"])
    return p, _by_rule([float(stats_row["poi_lo"])], [float(stats_row["poi_hi"])])


def test_stage_twos_verdict_is_stated_once_both_arms_are_complete_and_then_by_the_rule():
    """Stage 2's row in docs/reproduction.md's verdict table: "running", with no P, while an arm has fewer than its
    8 planned seeds (the count of runs in as the report has them); once both have 8, P(AdaRL > `parseval`) as the
    report computes it and the verdict the pre-registered rule gives, here and in README.md."""
    stats = {r["algorithm"]: r for r in csv.DictReader((REPORTS / "table1-decisive" / "statistics.csv").open())}
    n_adarl, n_parseval = int(stats["adarl"]["n_seeds"]), int(stats["parseval"]["n_seeds"])
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    arms, p_said, said_said = _verdict_row("Table 1: AdaRL above Parseval (1e-5)", DECISIVE)
    assert arms == "`adarl` 8, `parseval` 8", arms
    if min(n_adarl, n_parseval) < 8:
        assert p_said == "–" and said_said.startswith(f"running ({n_adarl + n_parseval} of 16 runs in"), said_said
        assert "the decisive stage (1e6 frames, 8 seeds each) is running" in readme
        return
    p, said = _by_the_rule(stats["parseval"])
    assert (p_said, said_said) == (p, said)
    assert f"P(AdaRL > Parseval) = {p} at 1e6 frames" in readme


def test_fig3_at_1e6_is_stated_once_sac_has_its_seeds_and_then_by_the_rule():
    """Fig. 3 at stage 2's budget (issue 45, decisive_sac): its row in reproduction.md's verdict table is "running"
    with no P while `sac_full` has fewer than its 8 seeds; once it has them, P(AdaRL > `sac_full`) as the report
    computes it, the pre-registered rule's verdict and the exact Mann-Whitney p, here and in README.md's Fig. 3 row.
    Its runs differ from stage 2's AdaRL in the algorithm alone (the resolved recipes: the SAC recipe's schedule,
    dense layers and no rank control; keys absent from the older commit's at their defaults)."""
    from scipy.stats import mannwhitneyu

    stats = {r["algorithm"]: r for r in csv.DictReader((REPORTS / "table1-decisive" / "statistics.csv").open())}
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    arms_of_fig3 = ("sac_full", "adarl")
    arms, p_said, said_said = _verdict_row("Fig. 3: AdaRL above full-rank SAC (issue 45)", DECISIVE)
    assert arms == "`adarl` 8, `sac_full` 8", arms
    n_sac = int(stats["sac_full"]["n_seeds"]) if "sac_full" in stats else 0
    if n_sac < 8:
        assert p_said == "–" and said_said.startswith("running"), said_said
        assert "Fig. 3 at 1e6 is running" in readme
        return
    p, said = _by_the_rule(stats["sac_full"])
    assert (p_said, said_said) == (p, said)
    scores: dict[str, list[float]] = {}
    for r in csv.DictReader((REPORTS / "table1-decisive" / "runs.csv").open()):
        scores.setdefault(r["algorithm"], []).append(float(r["score"]))
    mw = mannwhitneyu(scores["adarl"], scores["sac_full"], method="exact").pvalue
    assert f"P(AdaRL > SAC) = {p} at 1e6 frames" in readme and f"p = {mw:.3f}" in text, (p, mw)
    runs = REPORTS / "table1-decisive" / "runs"
    algorithm = {"name", "description", "lr_schedule.cosine", "lr_schedule.warmup_steps", "rank.enabled"}
    algorithm |= {"network.actor.low_rank_layers", "network.critic.low_rank_layers"}
    for s in range(8):
        sac, ada = (_flat_recipe(runs / f"env=hopper__algorithm={a}__seed={s}" / "recipe.yaml") for a in arms_of_fig3)
        assert set(_differences(sac, ada)) == algorithm, s


TABLE1_ROWS = ("Hopper", "Walker2d", "Ant", "Humanoid")
TABLE1_PAIRS = {"rnac_ds": 5, "rnac_ipm": 5, "parseval": 5, "sparse": 5, "sac_full": 8}  # X: its planned seeds


def test_table1s_row_verdicts_are_stated_once_each_pair_has_its_seeds_and_then_by_the_rule():
    """Issue 45's Table 1, row by row: reproduction.md's table "Table 1's verdicts, row by row" has one line per env and
    method X (20), with AdaRL's 8 and X's planned seeds; "queued" while the row has no report, "running" (no P, no p)
    while a side has fewer than its planned seeds; once both have them, P(AdaRL > X) as the row's paper_table.csv has
    it (the same as its statistics.csv), the exact Mann-Whitney p recomputed here from runs.csv's scores, and the
    pre-registered rule's verdict."""
    import re

    from scipy.stats import mannwhitneyu

    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    found = re.findall(r"\| (\w+) \| AdaRL vs [^|]*\(`(\w+)`\) \| 8, (\d+) \| ([^|]+) \| ([^|]+) \| ([^|]+?) \|", text)
    lines = {(env, x): rest for env, x, *rest in found}
    assert len(found) == len(lines) == 20 and {env for env, _ in lines} == set(TABLE1_ROWS), sorted(lines)
    for (env, x), (planned, p_said, mw_said, said) in lines.items():
        assert x in TABLE1_PAIRS and int(planned) == TABLE1_PAIRS[x], (env, x, planned)
        folder = REPORTS / f"table1-{env.lower()}"
        if not (folder / "paper_table.csv").exists():
            assert (p_said, mw_said, said) == ("–", "–", "queued"), (env, x)
            continue
        mine = {"env": env.lower()}.items()  # a row's report has every env's line in paper_table.csv
        row = {r["algorithm"]: r for r in csv.DictReader((folder / "paper_table.csv").open()) if mine <= r.items()}
        stats = {r["algorithm"]: r for r in csv.DictReader((folder / "statistics.csv").open()) if mine <= r.items()}
        n = {a: int(row[a]["n_seeds"]) for a in ("adarl", x)}
        if n["adarl"] < 8 or n[x] < int(planned):
            assert p_said == mw_said == "–" and said.startswith(("running", "queued")), (env, x, said)
            continue
        p, verdict = _by_the_rule(stats[x])
        assert _poi_text(row[x]["poi_ref"], row[x]["poi_lo"], row[x]["poi_hi"]) == p, (env, x)
        scores: dict[str, list[float]] = {}
        for r in csv.DictReader((folder / "runs.csv").open()):
            if r["env"] == env.lower():
                scores.setdefault(r["algorithm"], []).append(float(r["score"]))
        assert [len(scores[a]) for a in ("adarl", x)] == [n["adarl"], n[x]], (env, x)
        mw = mannwhitneyu(scores["adarl"], scores[x], method="exact").pvalue
        assert float(row[x]["mannwhitney_p"]) == pytest.approx(mw), (env, x)
        assert (p_said, mw_said) == (p, f"{mw:.3f}") and said.startswith(verdict), (env, x, p_said, mw_said, said)


def test_table1s_aggregate_across_rows_covers_exactly_the_complete_rows():
    """Issue 45's aggregate across Table 1's envs (docs/reports/table1, rliable's normalised scores: described, no rule)
    is made from the complete rows alone (every arm with its planned seeds), so that no method's pooled score mixes
    envs another method lacks: rows.txt names them, and its normalised scores are those rows' runs, one per run."""
    planned = {"adarl": 8, **TABLE1_PAIRS}
    complete = []
    for env in (e.lower() for e in TABLE1_ROWS):
        table = REPORTS / f"table1-{env}" / "paper_table.csv"
        if table.exists():
            n = {r["algorithm"]: int(r["n_seeds"]) for r in csv.DictReader(table.open()) if r["env"] == env}
            if all(n.get(a, 0) >= k for a, k in planned.items()):
                complete.append(env)
    folder = REPORTS / "table1"
    if not complete:
        assert not folder.exists()
        return
    rows = (folder / "rows.txt").read_text().split()
    assert rows == [f"docs/reports/table1-{env}/runs" for env in complete]
    per_run = list(csv.DictReader((folder / "normalised_scores.csv").open()))
    expected = [r for env in complete for r in csv.DictReader((REPORTS / f"table1-{env}" / "runs.csv").open())]
    assert sorted((r["env"], r["method"], r["seed"]) for r in per_run) == sorted(
        (r["env"], r["algorithm"], r["seed"]) for r in expected
    )
    for r, e in zip(
        sorted(per_run, key=lambda r: (r["env"], r["method"], int(r["seed"]))),
        sorted(expected, key=lambda r: (r["env"], r["algorithm"], int(r["seed"]))),
        strict=True,
    ):
        assert float(r["score"]) == pytest.approx(float(e["score"]))


def test_each_table1_rows_parseval_runs_at_its_envs_selected_lambda():
    """Parseval's lambda per env is the paper's selection (App. D.1: the best mean score of 1e-3, 1e-4, 1e-5 on the
    selection seeds 100-101), made before that row's Parseval arm: once an env's selection report has its 6 runs, the
    arm table1.yaml plans for that env resolves to the selected lambda; before, no Parseval run of that row is
    committed. Hopper's selection is issue 34's (docs/reports/parseval_lambda-laptop, the paper's physics)."""
    from adarl.experiments.spec import load_experiment, plan_runs
    from adarl.runtime.config import load_recipe

    spec = load_experiment(REPORTS.parents[1] / "recipes" / "experiments" / "table1.yaml")
    for env in (e.lower() for e in TABLE1_ROWS):
        folder = REPORTS / ("parseval_lambda-laptop" if env == "hopper" else f"parseval_lambda-laptop_{env}")
        rows = list(csv.DictReader((folder / "statistics.csv").open())) if (folder / "statistics.csv").exists() else []
        done = [r for r in rows if r["env"] == env and int(r["n_seeds"]) == 2]
        row_runs = REPORTS / f"table1-{env}" / "runs"
        if len(done) < 3:
            assert not list(row_runs.glob("*algorithm=parseval__*")), f"{env}: Parseval ran before its selection"
            continue
        selected = max(done, key=lambda r: float(r["mean"]))["lam"]
        (run,) = [r for r in plan_runs(spec, "/x", f"table1_{env}") if r.axes["algorithm"] == "parseval"][:1]
        lam = load_recipe(run.recipe, run.overrides).algorithm.parseval.lam
        assert lam == pytest.approx(float(selected)), (env, lam, selected)


def test_fig1s_verdict_is_stated_once_every_rank_is_complete_and_then_by_the_rule():
    """Fig. 1's row in docs/reproduction.md's verdict table: "running (N of 80 runs in" with no P while a rank has
    fewer than its 10 seeds; once all have 10, P(rank 8 > 4) and P(rank 8 > 16) as pairs.csv has them and the
    pre-registered rule's verdict (reproduced when both lower ends are above 0.5; contradicted when either upper
    end is below it), here and in README.md."""
    folder = REPORTS / "cartpole_rank_sweep-laptop_scored"
    counts = [int(r["n_seeds"]) for r in csv.DictReader((folder / "statistics.csv").open())]
    pairs = {(r["a"], r["b"]): r for r in csv.DictReader((folder / "pairs.csv").open())}
    arms, p, said = _verdict_row("Fig. 1: an interior optimum of the rank (linear CartPole)")
    assert arms == "8 ranks x 10 seeds", arms
    if len(counts) < 8 or min(counts) < 10:
        assert p == "–" and said.startswith(f"running ({sum(counts)} of 80 runs in"), (p, said)
        return
    want = "; ".join(
        f"P(8 > {b}) = {float(pairs['8', b]['poi']):.2f} [{float(pairs['8', b]['poi_lo']):.2f}, "
        f"{float(pairs['8', b]['poi_hi']):.2f}]"
        for b in ("4", "16")
    )
    verdict = _by_rule(
        [float(pairs["8", b]["poi_lo"]) for b in ("4", "16")], [float(pairs["8", b]["poi_hi"]) for b in ("4", "16")]
    )
    assert p == want and said.startswith(verdict), (p, said)
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    assert f"Fig. 1 (linear CartPole, 10 seeds per rank): {want}: {verdict}" in readme


def _verdict_row(claim: str, stage: str | None = None) -> tuple[str, str, str]:
    """(arms, P, verdict) of a claim's row in docs/reproduction.md's verdict table (its first cell starts with
    `claim`; with ``stage``, the row of that stage, e.g. :data:`DECISIVE`)."""
    import re

    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    where = re.escape(stage) if stage is not None else "[^|]+"
    row = re.search(r"\| " + re.escape(claim) + rf"[^|]*\| {where} \| ([^|]+) \| ([^|]+) \| ([^|]+?) \|", text)
    assert row, f"no row for {claim!r} in the verdict table"
    return row.group(1), row.group(2), row.group(3)


def _by_rule(lows: list[float], highs: list[float]) -> str:
    """The pre-registered rule over a claim's comparisons (each must be won: every lower end above 0.5)."""
    if min(lows) > 0.5:
        return "reproduced"
    return "contradicted" if min(highs) < 0.5 else "not reproduced (no difference shown)"


def test_table2s_verdict_is_stated_once_every_scope_is_complete_and_then_by_the_rule():
    """Table 2's row: "running (N of 15 runs in" (or "queued" before any run) with no P while a scope has fewer than
    5 seeds; then P(both > actor) and P(both > critic) as the report's statistics.csv has them, and the rule's
    verdict ("both is best": both lower ends above 0.5), here and in README.md."""
    folder = REPORTS / "table2-laptop"
    stats = {r["scope"]: r for r in csv.DictReader((folder / "statistics.csv").open())} if folder.is_dir() else {}
    scopes = ("actor", "critic", "both")  # the claim's arms (the follow-up's sac_full has its own row)
    counts = {k: int(r["n_seeds"]) for k, r in stats.items() if k in scopes}
    _, p, said = _verdict_row("Table 2:")
    if set(counts) != {"actor", "critic", "both"} or min(counts.values()) < 5:
        assert p == "–", p
        n = sum(counts.values())
        assert said.startswith(f"running ({n} of 15 runs in" if n else ("queued", "running (0 of 15")), said
        return
    want = "; ".join(
        f"P(both > {b}) = {float(stats[b]['poi_ref']):.2f} [{float(stats[b]['poi_lo']):.2f}, "
        f"{float(stats[b]['poi_hi']):.2f}]"
        for b in ("actor", "critic")
    )
    lows = [float(stats[b]["poi_lo"]) for b in ("actor", "critic")]
    highs = [float(stats[b]["poi_hi"]) for b in ("actor", "critic")]
    assert p == want and said.startswith(_by_rule(lows, highs)), (p, said)
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    assert f"Table 2 (Hopper, high uncertainty, 5 seeds per scope): {want}: {_by_rule(lows, highs)}" in readme


def _assert_differ_in_the_preset_alone(high: dict[int, dict], paper: dict[int, dict]) -> None:
    """Each seed's resolved recipe.yaml under the high box against the same seed's under the paper's schedule (runs.csv
    rows by seed): the same lines but ``env.perturbation.preset``."""
    for seed, row in high.items():
        ours = (REPORTS.parents[1] / row["path"] / "recipe.yaml").read_text().splitlines()
        theirs = (REPORTS.parents[1] / paper[seed]["path"] / "recipe.yaml").read_text().splitlines()
        differ = [(a.strip(), b.strip()) for a, b in zip(ours, theirs) if a != b]
        assert len(ours) == len(theirs) and differ == [("preset: high", "preset: paper")], (seed, differ)


def test_the_schedule_reading_is_its_runs_and_they_differ_in_the_schedule_alone():
    """reproduction.md's post-hoc reading "the training schedule moves AdaRL's score": Table 2's `both` seeds and the
    pilot's AdaRL seeds differ in ``env.perturbation.preset`` alone (their recipes, line by line), and the scores and
    post-hoc P stated are those of the committed runs, by the reports' estimator."""
    from adarl.experiments.report.stats import poi_estimate

    table2, pilot = REPORTS / "table2-laptop", REPORTS / "table1-pilot"
    both = {int(r["seed"]): r for r in csv.DictReader((table2 / "runs.csv").open()) if r["scope"] == "both"}
    adarl = {int(r["seed"]): r for r in csv.DictReader((pilot / "runs.csv").open()) if r["algorithm"] == "adarl"}
    assert sorted(both) == [0, 1, 2, 3, 4] and sorted(adarl) == list(range(8))
    _assert_differ_in_the_preset_alone(both, adarl)
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    high = [float(both[k]["score"]) for k in range(5)]
    paper5 = [float(adarl[k]["score"]) for k in range(5)]
    paper8 = [float(adarl[k]["score"]) for k in range(8)]
    p5, p8 = poi_estimate(high, paper5), poi_estimate(high, paper8)
    assert (
        f"score {', '.join(f'{v:.0f}' for v in high)} with Table 2's uniform lengths" in text
        and f"and {', '.join(f'{v:.0f}' for v in paper5)} with the paper's sinusoid" in text
    )
    assert f"P(high box > paper schedule) = {p5[0]:.2f} [{p5[1]:.2f}, {p5[2]:.2f}] (these five seeds; " in text
    assert f"{p8[0]:.2f} [{p8[1]:.2f}, {p8[2]:.2f}] against all eight pilot seeds)" in text


def test_the_follow_ups_verdict_is_stated_once_its_runs_are_in_and_then_by_the_rule():
    """The follow-up pre-registered 2026-11-27 06:52 UTC: "running (N of 5 runs in" with no P while full-rank SAC
    under the high box has fewer than 5 seeds; then P(both > sac_full) as Table 2's statistics.csv has it and the
    rule's verdict, here and in README.md."""
    stats = {r["scope"]: r for r in csv.DictReader((REPORTS / "table2-laptop" / "statistics.csv").open())}
    n = int(stats["sac_full"]["n_seeds"]) if "sac_full" in stats else 0
    _, p, said = _verdict_row("Follow-up: AdaRL above full-rank SAC under Table 2's high box")
    if n < 5:
        assert p == "–" and said.startswith(f"running ({n} of 5 runs in"), (p, said)
        return
    sac = stats["sac_full"]
    want = f"P(both > sac_full) = {float(sac['poi_ref']):.2f} [{float(sac['poi_lo']):.2f}, {float(sac['poi_hi']):.2f}]"
    rule = _by_rule([float(sac["poi_lo"])], [float(sac["poi_hi"])])
    assert p == want and said.startswith(rule), (p, said)
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    assert f"{want}: {rule}" in readme


def test_the_follow_ups_reading_is_its_runs_and_sac_differs_from_the_pilots_in_the_schedule_alone():
    """reproduction.md's follow-up bullet: the high-box SAC runs differ from the pilot's sac_full runs in the preset
    alone; their per-seed scores, means and the described P(sac_full high > paper schedule) are the runs'."""
    from adarl.experiments.report.stats import poi_estimate

    table2, pilot = REPORTS / "table2-laptop", REPORTS / "table1-pilot"
    high = {int(r["seed"]): r for r in csv.DictReader((table2 / "runs.csv").open()) if r["scope"] == "sac_full"}
    if len(high) < 5:
        pytest.skip("the follow-up's runs are not all in")
    paper = {int(r["seed"]): r for r in csv.DictReader((pilot / "runs.csv").open()) if r["algorithm"] == "sac_full"}
    _assert_differ_in_the_preset_alone(high, paper)
    h = [float(high[k]["score"]) for k in range(5)]
    p = [float(paper[k]["score"]) for k in range(5)]
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    poi = poi_estimate(h, p)
    seeds = ", ".join(f"{v:.0f}" for v in h)
    assert f"Full-rank SAC under the high box scores {seeds} (seeds 0-4; mean {statistics.mean(h):.0f}" in text
    assert f"= {poi[0]:.2f} [{poi[1]:.2f}, {poi[2]:.2f}] (seeds 0-4: {seeds} against " in text
    assert f"{', '.join(f'{v:.0f}' for v in p)}; means {statistics.mean(h):.0f} and {statistics.mean(p):.0f})" in text


def test_fig9s_verdict_is_stated_once_both_arms_are_complete_and_then_by_the_rule():
    """Fig. 9's row: no P while an arm has fewer than 5 seeds; then P(refill dips less than reset), re-derived here
    from event_window.csv (each seed's mean change over its events, the seed counted once) with the report's own
    estimator, and the rule's verdict, here and in README.md."""
    from adarl.experiments.report.stats import poi_estimate

    folder = REPORTS / "warmstart_ablation-laptop"
    seeds: dict[str, dict[str, list[float]]] = {}
    if (folder / "event_window.csv").is_file():
        for r in csv.DictReader((folder / "event_window.csv").open()):
            change = float(r["return_after"]) - float(r["return_before"])
            seeds.setdefault(r["warm_start"], {}).setdefault(r["seed"], []).append(change)
    done = (
        {
            arm: len({r["seed"] for r in csv.DictReader((folder / "runs.csv").open()) if r.get("warm_start") == arm})
            for arm in ("refill", "reset")
        }
        if (folder / "runs.csv").is_file()
        else {"refill": 0, "reset": 0}
    )
    _, p, said = _verdict_row("Fig. 9:")
    if min(done.values()) < 5:
        assert p == "–", p
        n = sum(done.values())
        assert said.startswith(f"running ({n} of 10 runs in" if n else ("queued", "running (0 of 10")), said
        return
    means = {arm: [statistics.fmean(v) for v in seeds[arm].values()] for arm in ("refill", "reset")}
    point, lo, hi = poi_estimate(means["refill"], means["reset"])
    want = f"P(refill dips less than reset) = {point:.2f} [{lo:.2f}, {hi:.2f}]"
    assert p == want and said.startswith(_by_rule([lo], [hi])), (p, said)
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    assert f"Fig. 9 (Hopper, 5 seeds per arm): {want}: {_by_rule([lo], [hi])}" in readme


def test_the_pilots_fig8_reading_is_its_sweeps():
    """docs/reproduction.md's Fig. 8 reading of the pilot (each arm's grid average and worst mean, the post-hoc
    P(AdaRL > `sac_full`) and P(AdaRL > `parseval`)) re-derived from every committed run's sweep summary."""
    import json
    import re

    from adarl.experiments.report.stats import poi_estimate

    runs = REPORTS / "table1-pilot" / "runs"
    per: dict[tuple[str, str], dict[int, dict]] = {}
    for f in sorted(runs.glob("*/sweeps/*.json")):
        arm, seed = re.search(r"algorithm=(\w+)__seed=(\d+)", f.parent.parent.name).groups()
        s = json.loads(f.read_text())
        per.setdefault((s["name"], arm), {})[int(seed)] = s
    arms = ("adarl", "sac_full", "sac_restarts", "parseval", "fixed_final", "factorised_restarts", "adarl_eq10")
    assert {a for _, a in per} == set(arms) and all(len(v) == (8 if a in arms[:3] else 5) for (_, a), v in per.items())
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())

    def arm_mean(arm, sweep, key):  # the report's grid-point means averaged over the grid = mean of the runs' averages
        return statistics.fmean(s[key] for s in per[sweep, arm].values())

    for key, label in (("average", "Grid average"), ("worst_mean", "Worst mean over the grid")):
        if key == "average":
            cells = [f"{arm_mean(a, 'torso_length', key):.0f} / {arm_mean(a, 'foot_length', key):.0f}" for a in arms]
        else:  # the report's worst mean: the lowest grid point of the across-seed mean curve
            cells = []
            for a in arms:
                worst = []
                for sweep in ("torso_length", "foot_length"):
                    curves = [
                        [float(r["mean"]) for r in csv.DictReader((runs / d / "sweeps" / f"{sweep}.csv").open())]
                        for d in sorted(p.name for p in runs.iterdir() if f"algorithm={a}__" in p.name)
                    ]
                    worst.append(min(statistics.fmean(col) for col in zip(*curves)))
                cells.append(f"{worst[0]:.0f} / {worst[1]:.0f}")
        said = ", ".join(f"{'AdaRL' if a == 'adarl' else f'`{a}`'} {c}" for a, c in zip(arms, cells))
        assert f"{label}, torso / foot: {said}" in text, said

    def p(arm, key, sweep):
        mine = [per[sweep, "adarl"][k][key] for k in sorted(per[sweep, "adarl"])]
        theirs = [per[sweep, arm][k][key] for k in sorted(per[sweep, arm])]
        return "{:.2f} [{:.2f}, {:.2f}]".format(*poi_estimate(mine, theirs))

    for arm in ("sac_full", "parseval"):
        want = (
            f"P(AdaRL > `{arm}`) on the grid average: torso {p(arm, 'average', 'torso_length')}, foot "
            f"{p(arm, 'average', 'foot_length')}; on the worst mean: torso {p(arm, 'worst_mean', 'torso_length')}, "
            f"foot {p(arm, 'worst_mean', 'foot_length')}"
        )
        assert want in text, want


def test_walker2ds_fig4_verdict_is_stated_once_its_seeds_are_in_and_then_by_the_rule():
    """Walker2d's Fig. 4 row: no verdict while fewer than its 5 seeds are in; then, per factorised layer, the rule
    (unchanged over the last event in at least half the seeds, median final rank within 1 of 2·d_a+1 = 13):
    "reproduced for" the layers that meet it, else "not reproduced (settle at ...)" with the median final ranks,
    as the committed rank_settling.csv has them."""
    folder = REPORTS / "rank_trajectory-laptop"
    rows = (
        list(csv.DictReader((folder / "rank_settling.csv").open())) if (folder / "rank_settling.csv").is_file() else []
    )
    seeds = {r["seed"] for r in rows}
    _, p, said = _verdict_row("Fig. 4 on Walker2d:")
    assert p == "–", p
    if len(seeds) < 5:
        assert said.startswith(f"running ({len(seeds)} of 5 runs in" if seeds else ("queued", "running (0 of 5")), said
        return
    layers = ("actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1")
    medians, met = [], []
    for layer in layers:
        mine = [r for r in rows if r["layer"] == layer]
        assert len(mine) == 5, layer
        median = statistics.median(int(r["final_rank"]) for r in mine)
        settled = sum(int(r["events_after_last_change"]) >= 1 for r in mine)
        medians.append(f"{median:g}")
        if 2 * settled >= len(mine) and abs(median - 13) <= 1:
            met.append(layer.replace(".layer", " layer "))
    want = "reproduced for " + ", ".join(met) if met else f"not reproduced (settle at {', '.join(medians)})"
    assert said.startswith(want), (said, want)


def test_the_pilots_stated_rank_settling_is_its_reports():
    """docs/reproduction.md's Fig. 4 reading of the pilot (median final ranks, Eq. 10's candidates at the last
    event, seeds unchanged over it) is the committed rank_settling.csv's."""
    rows = list(csv.DictReader((REPORTS / "table1-pilot" / "rank_settling.csv").open()))
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    finals, candidates, settled = [], [], []
    for layer in ("actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1"):
        mine = [r for r in rows if r["algorithm"] == "adarl" and r["layer"] == layer]
        assert len(mine) == 8, layer
        finals.append(f"{statistics.median(int(r['final_rank']) for r in mine):g}")
        candidates.append(f"{statistics.median(int(r['last_candidate']) for r in mine):g}")
        settled.append(str(sum(int(r["events_after_last_change"]) >= 1 for r in mine)))
    assert f"unchanged over the last event in {', '.join(settled[:-1])} and {settled[-1]} of 8 seeds" in text
    where = ("actor layer 0, of 11", "actor layer 1, of 64", "critic layer 0, of 14", "critic layer 1, of 64")
    assert "median final ranks " + ", ".join(f"{f} ({w})" for f, w in zip(finals, where)) in text
    assert f"medians {', '.join(candidates[:-1])} and {candidates[-1]}" in text


def test_walker2ds_stated_rank_settling_is_its_report():
    """docs/reproduction.md's Fig. 4 reading of Walker2d (seeds unchanged over the last event, median final ranks,
    the actor's input layer per seed, Eq. 10's candidates at the last event) is the committed rank_settling.csv's."""
    path = REPORTS / "rank_trajectory-laptop" / "rank_settling.csv"
    rows = list(csv.DictReader(path.open())) if path.is_file() else []
    if len({r["seed"] for r in rows}) < 5:
        pytest.skip("Walker2d's Fig. 4 runs are not all in")
    text = " ".join((REPORTS.parents[1] / "docs" / "reproduction.md").read_text().split())
    finals, candidates, settled = [], [], []
    for layer in ("actor.layer0", "actor.layer1", "critic.layer0", "critic.layer1"):
        mine = sorted((r for r in rows if r["layer"] == layer), key=lambda r: int(r["seed"]))
        assert len(mine) == 5, layer
        finals.append(f"{statistics.median(int(r['final_rank']) for r in mine):g}")
        candidates.append(f"{statistics.median(int(r['last_candidate']) for r in mine):g}")
        settled.append(str(sum(int(r["events_after_last_change"]) >= 1 for r in mine)))
        if layer == "actor.layer0":
            first = ", ".join(r["final_rank"] for r in mine)
    assert f"unchanged over the last event in {', '.join(settled[:-1])} and {settled[-1]} of 5 seeds" in text
    where = ("actor layer 0, of 17", "actor layer 1, of 64", "critic layer 0, of 23", "critic layer 1, of 64")
    assert "median final ranks are " + ", ".join(f"{f} ({w})" for f, w in zip(finals[:-1], where)) in text
    assert f"and {finals[-1]} ({where[-1]})" in text and f"the actor's input layer ends at {first}," in text
    assert f"medians {', '.join(candidates[:-1])} and {candidates[-1]}:" in text
    row = _verdict_row("Fig. 4 on Walker2d:")[2]
    others = ", ".join(finals[1:])
    assert (
        f"(median final rank {finals[0]} = 2·d_a+1, unchanged over the last event in {settled[0]} of 5 seeds; " in row
    )
    assert f"the other layers settle at {others}; Eq. 10's own candidate for actor layer 0 is {candidates[0]})" in row


def test_parsevals_lambda_at_the_papers_physics_is_stated_as_its_report_has_it():
    """reproduction.md's Parseval-lambda bullet: the value with the highest mean score is 1e-5, the one the pilot's
    and stage 2's Parseval arms run, and each stated mean (and per-seed score) is the committed report's."""
    import yaml

    folder = REPORTS / "parseval_lambda-laptop"
    stats = {r["lam"]: r for r in csv.DictReader((folder / "statistics.csv").open())}
    runs = list(csv.DictReader((folder / "runs.csv").open()))
    assert {k: int(r["n_seeds"]) for k, r in stats.items()} == {"1.0e-3": 2, "1.0e-4": 2, "1.0e-5": 2}
    assert all(r["score_last"] == "3" for r in runs)  # the protocol's score
    best = max(stats, key=lambda k: float(stats[k]["mean"]))
    spec = yaml.safe_load((REPORTS.parents[1] / "recipes" / "experiments" / "table1.yaml").read_text())
    arms = {a["name"]: a for a in spec["axes"]["algorithm"] if isinstance(a, dict)}
    assert f"algorithm.parseval.lam={best}" in arms["parseval"]["overrides"]  # the arm runs the selected value
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())

    def seeds(lam):
        return ", ".join(f"{float(r['score']):.0f}" for r in sorted(runs, key=lambda r: r["seed"]) if r["lam"] == lam)

    said = "; ".join(
        f"{lam.replace('1.0e', '1e')} {float(stats[lam]['mean']):.0f} ({seeds(lam)})" for lam in ("1.0e-5",)
    )
    assert "1e-5 is selected again**" in text and f"three evaluations): {said}" in text
    for lam in ("1.0e-4", "1.0e-3"):
        assert f"{lam.replace('1.0e', '1e')} {float(stats[lam]['mean']):.0f} ({seeds(lam)})" in text, lam


def test_every_protocol_report_is_made_by_its_rule():
    """commit_landed.sh commits each protocol experiment's runs into a report folder; make_report.sh must re-make
    every such folder from its own spec's report section (else a report lands without its verdicts), and Fig. 1's
    spec must name the protocol's pairs."""
    import re

    import yaml

    issue34 = REPORTS / "issue34"
    landed = re.search(r"for pair in (.*?); do", (issue34 / "commit_landed.sh").read_text(), re.S).group(1)
    folders = {p.split(":")[-1] for p in landed.replace("\\", " ").split()}
    specs = dict(re.findall(r"^\s*([\w|-]+)\) spec=(\w+)[^\n]*;;", (issue34 / "make_report.sh").read_text(), re.M))
    made = {folder: spec for names, spec in specs.items() for folder in names.split("|")}
    assert folders == set(made), folders ^ set(made)
    root = REPORTS.parents[1] / "recipes" / "experiments"
    for spec in set(made.values()):
        assert (root / f"{spec}.yaml").is_file(), spec
    cartpole = yaml.safe_load((root / "cartpole_rank_sweep.yaml").read_text())["report"]
    assert cartpole["pairs"] == [["8", "4"], ["8", "16"]] and cartpole["score_last"] == 3


def test_the_stated_multiplicity_is_the_reports():
    """README.md's and reproduction.md's words on multiplicity (issue 45): the pairs the protocol judged by the 95%
    rule, counted from the committed reports (19, of which 8 "beats", all at the pilot); each "beats"' exact
    Mann-Whitney p as stated (none survives Holm over the 19, one over the pilot's 12); and the post-hoc
    P(factorised_restarts > sac_full) as the report's estimator gives it, with its upper end on 0.5 at most bootstrap
    seeds (as P(AdaRL > fixed_final)'s)."""
    from scipy.stats import mannwhitneyu

    from adarl.experiments.report.stats import poi_estimate

    def rows(folder: str, name: str) -> list[dict]:  # a pair still waiting for its seeds is not judged yet
        found = csv.DictReader((REPORTS / folder / name).open())
        return [r for r in found if not (r.get("verdict") or "").startswith("waits for")]

    def bounds(r: dict) -> tuple[float, float]:
        return float(r["poi_lo"]), float(r["poi_hi"])

    judged = [  # (report, a, b, (low, high)) of every pair the protocol judged
        *(("pilot", "adarl", r["algorithm"], bounds(r)) for r in rows("table1-pilot", "statistics.csv")),
        *(("pilot", r["a"], r["b"], bounds(r)) for r in rows("table1-pilot", "pairs.csv")),
        *(  # the decisive stage's AdaRL vs Parseval; its sac_full row is issue 45's (Fig. 3 at 1e6), counted apart
            ("decisive", "adarl", r["algorithm"], bounds(r))
            for r in rows("table1-decisive", "statistics.csv")
            if r["algorithm"] != "sac_full"
        ),
        *(("table2", "both", r["scope"], bounds(r)) for r in rows("table2-laptop", "statistics.csv")),
        *(("fig1", r["a"], r["b"], bounds(r)) for r in rows("cartpole_rank_sweep-laptop_scored", "pairs.csv")),
    ]
    judged = [j for j in judged if j[1] != j[2]]  # a report's reference row is no pair
    dips: dict[str, dict[str, list[float]]] = {}
    for r in rows("warmstart_ablation-laptop", "event_window.csv"):
        change = float(r["return_after"]) - float(r["return_before"])
        dips.setdefault(r["warm_start"], {}).setdefault(r["seed"], []).append(change)
    means = {arm: [statistics.fmean(v) for v in seeds.values()] for arm, seeds in dips.items()}
    judged.append(("fig9", "refill", "reset", poi_estimate(means["refill"], means["reset"])[1:]))
    beats = [(where, a, b) for where, a, b, (lo, hi) in judged if lo > 0.5 or hi < 0.5]
    assert len(judged) == 19 and len(beats) == 8 and {where for where, _, _ in beats} == {"pilot"}
    readme = " ".join((REPORTS.parents[1] / "README.md").read_text().split())
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    assert "judged 19 pairs by the 95% rule (12 at the pilot, 1 at the decisive stage, 3 for Table 2" in readme
    assert '8 gave "beats" (all at the pilot), 11 "no difference shown"' in readme
    assert "judged 19 pairs by the rule" in text and '8 of the 19 gave "beats", all at the pilot' in text
    pilot: dict[str, list[float]] = {}
    for r in rows("table1-pilot", "runs.csv"):
        pilot.setdefault(r["algorithm"], []).append(float(r["score"]))
    p = {(a, b): mannwhitneyu(pilot[a], pilot[b], method="exact").pvalue for _, a, b in beats}
    ps = sorted(p.values())
    assert ps[0] > 0.05 / 19 and ps[0] < 0.05 / 12 < 0.05 / 11 < ps[1]  # Holm: none over 19, one over the pilot's 12
    said = (
        f"p = {p['adarl_eq10', 'sac_full']:.3f} (`adarl_eq10` vs `sac_full`), {p['adarl_eq10', 'sac_restarts']:.3f} "
        f"(vs `sac_restarts`), {p['adarl_eq10', 'parseval']:.3f} (vs `parseval`), {p['adarl', 'sac_restarts']:.3f} "
        f"(AdaRL vs `sac_restarts`), {p['adarl', 'sac_full']:.3f} (AdaRL vs `sac_full`), "
        f"{p['adarl_eq10', 'fixed_final']:.3f} (`adarl_eq10` vs `fixed_final`), {p['adarl', 'parseval']:.3f} (AdaRL "
        f"vs `parseval` at 300k) and {p['factorised_restarts', 'sac_restarts']:.3f} (`factorised_restarts` vs"
    )
    assert said in text, said
    near = sorted(ps[-3:])
    assert 0.05 < near[0] and f"p = {near[0]:.3f}-{near[-1]:.3f}" in readme  # the three nearest the threshold
    post = poi_estimate(pilot["factorised_restarts"], pilot["sac_full"])
    stated = f"{post[0]:.2f} [{post[1]:.2f}, {post[2]:.2f}]"
    assert f"P(`factorised_restarts` > `sac_full`) = {stated}" in text and f"P(never cut > SAC) = {stated}" in readme
    for a, b in (("factorised_restarts", "sac_full"), ("adarl", "fixed_final")):
        highs = [poi_estimate(pilot[a], pilot[b], seed=s)[2] for s in range(20)]
        assert sum(h < 0.5 for h in highs) == 4 and all(h <= 0.5 for h in highs), (a, b)
    assert "its upper end is 0.50 at 16 of 20 bootstrap seeds" in readme


# -- issue 45: the mechanism arms (docs/reproduction.md, "Issue 45: what costs the factorised networks") -----------

MECHANISM = {  # arm (a)-(d): (its base, the one recipe key it changes, its value)
    "adarl_project": ("adarl", "rank.target_mode", "project"),
    "factorised_product": ("factorised_restarts", "algorithm.polyak", "product"),
    "factorised_lr": ("factorised_restarts", "algorithm.factor_lr_scale", 0.82),
    "factorised_torchrl": ("factorised_restarts", "algorithm.fused", False),
}
# arm (e), by its amendment (run only when none of (a)-(d) counts): one choice, the factors' initialisation, set on both
# networks as (b)-(d) act on both
ARM_E = ("factorised_init", "factorised_restarts", ("network.actor.init.scheme", "network.critic.init.scheme"))


def _flat_recipe(path: Path) -> dict:
    import yaml

    def walk(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from walk(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    return dict(walk(yaml.safe_load(path.read_text())))


def _differences(ours: dict, theirs: dict) -> dict:
    """Keys whose values differ, less the keys an older adarl did not write (theirs lacks them) at today's defaults."""
    from adarl.runtime.config import load_recipe

    defaults = _flat_recipe_from(load_recipe("hopper_adarl").model_dump(mode="json"))
    out = {}
    for key in sorted(set(ours) | set(theirs)):
        if key not in theirs and ours.get(key) == defaults.get(key, object()):
            continue  # added since the older run's commit, at its default
        if key not in theirs and key == "plugins" and ours[key] == []:
            continue
        if ours.get(key, "<absent>") != theirs.get(key, "<absent>"):
            out[key] = (ours.get(key, "<absent>"), theirs.get(key, "<absent>"))
    return out


def _flat_recipe_from(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_flat_recipe_from(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_issue45s_landed_mechanism_runs_differ_from_their_bases_in_their_key_alone():
    """Every committed run of a mechanism arm against the same seed of its base (the pilot's adarl for (a), the
    re-run factorised_restarts for (b)-(d)): their resolved recipes differ in the arm's key alone; the re-run
    factorised_restarts against the pilot's (commit 579fa0b) in nothing but keys added since at their defaults."""
    runs = REPORTS / "mechanism-pilot" / "runs"
    pilot = REPORTS / "table1-pilot" / "runs"
    landed = sorted(runs.glob("env=hopper__algorithm=*__seed=*")) if runs.is_dir() else []
    arms = {arm: (base, {key: value}) for arm, (base, key, value) in MECHANISM.items()}
    arms[ARM_E[0]] = (ARM_E[1], dict.fromkeys(ARM_E[2], "independent_factors"))
    for run in landed:
        arm, seed = run.name.split("__algorithm=")[1].split("__seed=")
        ours = _flat_recipe(run / "recipe.yaml")
        if arm in arms:
            base, changed = arms[arm]
            base_dir = (pilot if base == "adarl" else runs) / f"env=hopper__algorithm={base}__seed={seed}"
            if not base_dir.is_dir():
                continue  # its base's seed has not landed yet
            theirs = _flat_recipe(base_dir / "recipe.yaml")  # the pilot's (579fa0b) lack keys added since: absent
            assert _differences(ours, theirs) == {k: (v, theirs.get(k, "<absent>")) for k, v in changed.items()}, (
                run.name
            )
        elif arm == "factorised_restarts" and (pilot / run.name).is_dir():
            assert _differences(ours, _flat_recipe(pilot / run.name / "recipe.yaml")) == {}, run.name
    # the spec's arms are these (and its bases are the pilot's arms of the same names)
    import yaml

    spec = yaml.safe_load((REPORTS.parents[1] / "recipes" / "experiments" / "mechanism.yaml").read_text())
    values = {v["name"]: v.get("overrides", []) for v in spec["axes"]["algorithm"]}
    for arm, (base, changed) in arms.items():
        want = {f"{k}={'false' if v is False else v}" for k, v in changed.items()}
        assert want <= set(values[arm]) and set(values[arm]) - want <= set(values[base] + ["rank.truncate=false"])
    # arm (e)'s budget is the pilot's, for that arm alone
    budgets = spec["budgets"]
    assert budgets["pilot_init"]["axes"] == {"algorithm": [ARM_E[0]]}
    assert budgets["pilot_init"]["overrides"] == budgets["pilot"]["overrides"]
    assert [ARM_E[0], ARM_E[1]] in spec["report"]["pairs"] and [ARM_E[0], "sac_restarts"] in spec["report"]["pairs"]


def test_issue45s_mechanism_status_claims_no_more_than_its_report():
    """reproduction.md states the mechanism arms' progress as "running (N of 40 runs in" with no P before every arm
    has its 8 seeds: N is at most the committed count (the commit loop may have landed more since), and no
    "counts" verdict is written before then."""
    import re

    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    stats = REPORTS / "mechanism-pilot" / "statistics.csv"
    rows = {r["algorithm"]: r for r in csv.DictReader(stats.open())} if stats.is_file() else {}
    arms = ["factorised_restarts", *MECHANISM]
    counts = {a: int(rows[a]["n_seeds"]) if a in rows else 0 for a in arms}
    said = re.search(r"mechanism arms: running \((\d+) of 40 runs in", text)
    if min(counts.values()) < 8:
        assert said, "the mechanism arms' status line is missing"
        assert int(said.group(1)) <= sum(counts.values()), (said.group(1), counts)
        assert "counts (the lower end above 0.5)" not in text
    else:  # complete: the status line gives way to the verdicts (written by the session that sees them in)
        assert not said or int(said.group(1)) == 40


def test_issue45s_factorisation_pair_is_stated_as_its_report_decides_it():
    """The one mechanism pair decided so far (8 seeds a side): reproduction.md and the README state its P and
    interval as pairs.csv has them, with the pre-registered word ("supported" only when the report's verdict is
    sac_restarts beats factorised_restarts), and the Mann-Whitney p recomputed from runs.csv."""
    from scipy.stats import mannwhitneyu

    pairs = {(r["a"], r["b"]): r for r in csv.DictReader((REPORTS / "mechanism-pilot" / "pairs.csv").open())}
    pair = pairs[("factorised_restarts", "sac_restarts")]
    if int(pair["n_a"]) < 8 or int(pair["n_b"]) < 8:
        return
    said = f"= {float(pair['poi']):.2f} [{float(pair['poi_lo']):.2f}, {float(pair['poi_hi']):.2f}]"
    scores: dict[str, list[float]] = {}
    for r in csv.DictReader((REPORTS / "mechanism-pilot" / "runs.csv").open()):
        scores.setdefault(r["algorithm"], []).append(float(r["score"]))
    p = mannwhitneyu(scores["factorised_restarts"], scores["sac_restarts"], method="exact").pvalue
    supported = pair["verdict"] == "sac_restarts beats factorised_restarts"
    for doc in (REPORTS.parent / "reproduction.md", REPORTS.parents[1] / "README.md"):
        text = " ".join(doc.read_text().split())
        at = text.index("> `sac_restarts`) " + said) if doc.name == "reproduction.md" else text.index(said)
        window = text[max(0, at - 400) : at + 400]
        assert f"Mann-Whitney p = {p:.3f}" in window, (doc.name, p)
        assert ("**supported**" in window or "**supports**" in window) == supported, doc.name


def test_issue45s_decided_mechanism_arms_are_stated_as_their_report_decides_them():
    """Each mechanism arm on factorised_restarts with 8 seeds a side (arm (c) first): reproduction.md states its P and
    interval against factorised_restarts and against sac_restarts as pairs.csv has them, the exact Mann-Whitney p of
    each recomputed from runs.csv, and "does **not count**" exactly when its interval against its base includes 0.5
    (the pre-registered rule: a choice counts only if that interval excludes 0.5)."""
    from scipy.stats import mannwhitneyu

    pairs = {(r["a"], r["b"]): r for r in csv.DictReader((REPORTS / "mechanism-pilot" / "pairs.csv").open())}
    scores: dict[str, list[float]] = {}
    for r in csv.DictReader((REPORTS / "mechanism-pilot" / "runs.csv").open()):
        scores.setdefault(r["algorithm"], []).append(float(r["score"]))
    text = " ".join((REPORTS.parent / "reproduction.md").read_text().split())
    decided = 0
    for arm in ("factorised_lr", "factorised_product", "factorised_torchrl", ARM_E[0]):
        rows = [pairs.get((arm, base)) for base in ("factorised_restarts", "sac_restarts")]
        if any(r is None or int(r["n_a"]) < 8 or int(r["n_b"]) < 8 for r in rows):
            continue
        decided += 1
        for row in rows:
            said = f"P(`{arm}` > `{row['b']}`) = {float(row['poi']):.2f} [{float(row['poi_lo']):.2f}, "
            said += f"{float(row['poi_hi']):.2f}]"
            at = text.index(said)
            p = mannwhitneyu(scores[arm], scores[row["b"]], method="exact").pvalue
            assert f"Mann-Whitney p = {p:.2f}" in text[at : at + 200] or f"(p = {p:.2f})" in text[at : at + 200], (
                arm,
                row["b"],
                p,
            )
        base = rows[0]  # the registered words: counts (above 0.5), makes the return worse (below), or neither
        lo, hi = float(base["poi_lo"]), float(base["poi_hi"])
        at = text.index(f"P(`{arm}` > `factorised_restarts`)")
        window = text[at : at + 600]
        assert ("does **not count**" in window) == (lo <= 0.5 <= hi), arm
        assert ("**makes the return worse**" in window) == (hi < 0.5), arm
        if lo > 0.5:
            assert "**counts**" in window and "does **not count**" not in window, arm
    assert decided >= 1  # factorised_lr has its 8 seeds (committed 2026-11-27)


def test_issue45s_arm_e_runs_only_when_no_arm_counts():
    """arm_e_due.py (queue.sh asks it after arms (a)-(d)) applies the amendment's rule: (e) is due (0) when none of the
    four "counts" pairs has its interval above 0.5, not run (1) when one has, and undecided (2) before every pair has 8
    seeds a side; on the committed mechanism report it says what that report's pairs say."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("arm_e_due", REPORTS / "issue45" / "arm_e_due.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    def write(path, lows, n=8):
        rows = [
            {"env": "hopper", "a": a, "b": b, "n_a": n, "n_b": 8, "poi": lo + 0.2, "poi_lo": lo, "poi_hi": lo + 0.4}
            for (a, b), lo in zip(module.COUNTS, lows)
        ]
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        return path

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "pairs.csv"
        assert module.decide(write(f, [0.2, 0.3, 0.1, 0.5]))[0] == 0  # 0.5 is not above 0.5
        code, why = module.decide(write(f, [0.2, 0.3, 0.52, 0.1]))
        assert code == 1 and "factorised_product" in why
        assert module.decide(write(f, [0.2, 0.3, 0.1, 0.1], n=7))[0] == 2
    committed = {(r["a"], r["b"]): r for r in csv.DictReader((REPORTS / "mechanism-pilot" / "pairs.csv").open())}
    rows = [committed.get(pair) for pair in module.COUNTS]
    code, _ = module.decide(REPORTS / "mechanism-pilot" / "pairs.csv")
    if any(r is None or min(int(r["n_a"] or 0), int(r["n_b"] or 0)) < 8 for r in rows):
        assert code == 2
    else:
        assert code == (1 if any(float(r["poi_lo"]) > 0.5 for r in rows) else 0)


def test_issue45s_landed_runs_are_made_into_a_report_by_their_rule():
    """issue45/commit_landed.sh commits each experiment's runs into a report folder that issue45/make_report.sh
    re-makes from its spec's report section (else runs land without their verdicts), and every experiment folder
    queue.sh fills is one the loop exports."""
    import re

    issue45 = REPORTS / "issue45"
    text = (issue45 / "commit_landed.sh").read_text().replace("\\\n", " ")
    pairs = [p.split(":") for p in re.search(r"for pair in (.*?); do", text, re.S).group(1).split()]
    landed, exported = {report for report, _ in pairs}, {folder for _, folder in pairs}
    made = (issue45 / "make_report.sh").read_text()
    specs, delegated = {}, {}
    for names, spec, issue, name in re.findall(
        r"^\s*([\w| -]+)\)\s*(?:spec=(\w+)|exec bash docs/reports/(issue\d+)/make_report.sh ([\w-]+))", made, re.M
    ):
        for case in (n.strip() for n in names.split("|")):
            if spec:
                specs[case] = spec
            else:
                delegated[case] = (issue, name)
    assert landed == set(specs) | set(delegated)
    for spec in specs.values():
        assert (REPORTS.parents[1] / "recipes" / "experiments" / f"{spec}.yaml").is_file(), spec
    for issue, name in delegated.values():  # the other script makes that folder (its case exists)
        assert re.search(rf"^\s*{re.escape(name)}\) spec=\w+", (REPORTS / issue / "make_report.sh").read_text(), re.M)
    queued = set(re.findall(r" -o /work/exp/([\w$-]+)", (issue45 / "queue.sh").read_text()))
    queued = {q.replace("$env", env) for q in queued for env in ("walker2d", "ant", "humanoid")}
    assert queued == exported, (queued, exported)


def test_copies_of_the_committed_pilot_runs_are_finished_runs_of_its_spec_and_an_edited_one_is_named(tmp_path):
    """Issue 46: an experiment reuses a finished run only while its recipe is what the spec plans now. The committed
    runs (made before run folders recorded a fingerprint, by an adarl without algorithm.polyak and
    algorithm.factor_lr_scale) are copied into experiment folders to be reused (issue45/fresh_machine.sh,
    issue34/fresh_machine.sh): their recipe.yaml, validated by today's schema, must still be the plan's, so a dry run
    over copies reports them finished; a copy whose recipe says another rank.beta is named with the key."""
    import shutil

    import yaml

    from adarl.experiments.orchestrate import run_experiment

    picked = [f"env=hopper__algorithm={arm}__seed={s}" for arm, s in (("adarl", 0), ("adarl", 1), ("sac_restarts", 0))]
    picked.append("env=hopper__algorithm=parseval__seed=0")
    out = tmp_path / "table1-pilot"
    for name in picked:
        shutil.copytree(REPORTS / "table1-pilot" / "runs" / name, out / name)
        assert not (out / name / "fingerprint.json").exists()  # made before the fingerprint
    assert "polyak" not in (out / picked[0] / "recipe.yaml").read_text()  # and before the key
    spec = REPORTS.parents[1] / "recipes" / "experiments" / "table1.yaml"
    said: list[str] = []
    runs = {r.run_id: r for r in run_experiment(spec, budget="pilot", output=out, dry_run=True, log=said.append)}
    assert [runs[name].status for name in picked] == ["skipped-finished"] * 4, said
    assert {r.status for n, r in runs.items() if n not in picked} == {"pending"}
    edited = out / picked[1] / "recipe.yaml"
    recipe = yaml.safe_load(edited.read_text())
    recipe["rank"]["beta"] = 0.9
    edited.write_text(yaml.safe_dump(recipe, sort_keys=False))
    said.clear()
    runs = {r.run_id: r for r in run_experiment(spec, budget="pilot", output=out, dry_run=True, log=said.append)}
    expected = ["skipped-finished", "changed", "skipped-finished", "skipped-finished"]
    assert [runs[name].status for name in picked] == expected, said
    assert any(picked[1] in line and "rank.beta: 0.9 in the run, 0.98 in the spec" in line for line in said), said


def test_issue45s_row_facts_quote_the_rows_report(capsys):
    """row_facts.py (what a row's verdict paragraph quotes) reads the row's own env from the report: every pair it
    prints has the P [CI], exact p and verdict of paper_table.csv's row for that env (the report holds all four envs'
    paper rows, so a reader keyed by method alone would quote another env's)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("row_facts", REPORTS / "issue45" / "row_facts.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main([str(REPORTS / "table1-walker2d")])
    out = capsys.readouterr().out
    paper = [
        r for r in csv.DictReader((REPORTS / "table1-walker2d" / "paper_table.csv").open()) if r["env"] == "walker2d"
    ]
    decided = [r for r in paper if r["verdict"]]
    assert len(decided) == 5  # the row is complete: five pairs
    for r in decided:
        line = (
            f"P(adarl > {r['algorithm']}) = {float(r['poi_ref']):.2f} [{float(r['poi_lo']):.2f}, "
            f"{float(r['poi_hi']):.2f}], exact p = {float(r['mannwhitney_p']):.3f}: {r['verdict']}"
        )
        assert line in out, line
    for r in paper:
        if r["paper_mean"]:
            assert f"walker2d {r['algorithm']}: " in out and f"paper {r['paper_mean']};" in out
    # the described, no-rule reading: each method's mean curve at 300k frames and AdaRL's final ranks per layer
    curves = list(csv.DictReader((REPORTS / "table1-walker2d" / "learning_curves.csv").open()))
    blocks = out.split("walker2d ")[1:]
    for r in decided:
        (block,) = [b for b in blocks if b.startswith(f"{r['algorithm']}: ")]
        (last,) = [
            c for c in curves if c["group"] == f"env=walker2d, algorithm={r['algorithm']}" and c["frames"] == "300000"
        ]
        assert f", 300k {float(last['mean']):.0f}\n" in block
    settling = [r for r in csv.DictReader((REPORTS / "table1-walker2d" / "rank_settling.csv").open())]
    (adarl,) = [b for b in blocks if b.startswith("adarl: ")]
    for layer in {r["layer"] for r in settling}:
        final = sorted(int(r["final_rank"]) for r in settling if r["layer"] == layer)
        assert (
            f"rank {layer}: " in adarl and f" -> {final[0]}-{final[-1]} (median " in adarl.split(f"rank {layer}: ")[1]
        )
