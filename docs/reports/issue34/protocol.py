"""Issue 34's pre-registered decisions, computed from finished run folders (docs/reproduction.md, the protocol).

fixed-final DIR: per factorised layer, the median (rounded half up) of AdaRL's final ranks over the pilot's seeds;
                 writes extra_recipes/baselines/hopper_sac_fixed_final.yaml.
strongest DIR:   the control arm with the highest mean pilot score (score = mean of the last three nominal evals);
                 writes table1_decisive.yaml (the spec with the decisive budget's second arm).
"""

import csv
import json
import math
import statistics
import sys
from pathlib import Path

EXP = Path("/work/exp")


def score(run: Path) -> float:
    rows = list(csv.DictReader((run / "eval.csv").open()))
    return statistics.fmean(float(r["mean"]) for r in rows[-3:])


def finished(run: Path) -> bool:
    return (run / "summary.json").is_file()


def fixed_final(out: Path) -> None:
    runs = sorted(p for p in out.glob("env=hopper__algorithm=adarl__seed=*") if finished(p))
    assert len(runs) == 8, [p.name for p in runs]
    finals: dict[str, list[int]] = {}
    for run in runs:
        history = json.loads((run / "ranks.json").read_text())
        last: dict[str, int] = {}
        for event in history:
            for layer in event["layers"]:
                last[layer["name"]] = int(layer["new_rank"])
        for name, rank in last.items():
            finals.setdefault(name, []).append(rank)
    med = {n: math.floor(statistics.median(v) + 0.5) for n, v in sorted(finals.items())}
    record = {"finals": finals, "median_rounded_half_up": med, "runs": [p.name for p in runs]}
    (EXP / "fixed_final.json").write_text(json.dumps(record, indent=2))
    actor = [med["actor.layer0"], med["actor.layer1"]]
    critic = [med["critic.layer0"], med["critic.layer1"]]
    (EXP / "extra_recipes/baselines/hopper_sac_fixed_final.yaml").write_text(
        f"""extends: baselines/hopper_sac_fixed
name: hopper_sac_fixed_final
description: "Control: SAC fixed from the start at AdaRL's final ranks (pilot medians) on perturbed Hopper-v5"

# Issue 34's fixed_final arm: per layer, the median (rounded half up) of the final ranks of table1 --budget pilot's
# 8 AdaRL seeds: {json.dumps(finals)}
network:
  actor: {{rank: {actor}}}
  critic: {{rank: {critic}}}
"""
    )
    print("fixed_final ranks:", med)


def strongest(*outs: Path) -> None:
    arms = ["sac_full", "sac_restarts", "fixed_final", "parseval"]
    means = {}
    for arm in arms:
        runs = sorted(p for out in outs for p in out.glob(f"env=hopper__algorithm={arm}__seed=*") if finished(p))
        assert len(runs) == (8 if arm in ("sac_full", "sac_restarts") else 5), (arm, [p.name for p in runs])
        means[arm] = statistics.fmean(score(p) for p in runs)
    best = max(means, key=means.get)
    (EXP / "strongest_control.json").write_text(json.dumps({"mean_scores": means, "strongest": best}, indent=2))
    spec = (EXP / "wt-g/recipes/experiments/table1.yaml").read_text()
    old = "    axes: {env: [hopper], algorithm: [adarl]}\n    overrides: [collector.total_frames=1000000"
    assert old in spec
    spec = spec.replace(old, old.replace("algorithm: [adarl]", f"algorithm: [adarl, {best}]"))
    (EXP / "table1_decisive.yaml").write_text(spec)
    print("mean pilot scores:", means, "-> strongest control:", best)


if __name__ == "__main__":
    {"fixed-final": fixed_final, "strongest": strongest}[sys.argv[1]](*map(Path, sys.argv[2:]))
