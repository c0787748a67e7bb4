"""Copy each finished run's small files (recipe, evaluations, ranks, summary, the metric CSVs the reports read,
sweeps) from an experiment folder into a committed report folder's runs/ (issue 34: "commit each finished run's
small files as it lands"). Checkpoints, buffers and plots stay behind. Prints the runs it copied.

    python docs/reports/issue34/export_runs.py /work/exp/table1-pilot docs/reports/table1-pilot
"""

import shutil
import sys
from pathlib import Path

from adarl.experiments.execute import run_is_finished

SMALL = [
    "recipe.yaml",
    "eval.csv",
    "summary.json",
    "ranks.json",
    "ranks.csv",
    "plugins.json",
    "metrics/scalars/train/episode_return.csv",
    "metrics/scalars/eval/return.csv",
    "metrics/scalars/warm_start/frames.csv",
    "metrics/scalars/train/updates.csv",  # optimisation steps at each log: places rank events in frames (figures)
    "metrics/scalars/train/n_updates.csv",  # its name since issue 31
]


def export(exp: Path, report: Path) -> list[str]:
    copied = []
    for run in sorted(p.parent for p in exp.glob("*/summary.json") if run_is_finished(p.parent)):
        dest = report / "runs" / run.name
        files = [f for f in SMALL if (run / f).is_file()]
        files += [str(p.relative_to(run)) for p in sorted((run / "sweeps").glob("*.csv"))]
        files += [str(p.relative_to(run)) for p in sorted((run / "sweeps").glob("*.json"))]
        changed = False
        for f in files:
            target = dest / f
            if not target.is_file() or target.read_bytes() != (run / f).read_bytes():
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(run / f, target)
                changed = True
        if changed:
            copied.append(run.name)
    return copied


if __name__ == "__main__":
    for name in export(Path(sys.argv[1]), Path(sys.argv[2])):
        print(name)
