"""Is issue 45's arm (e) due? The rule its amendment pre-registered (docs/reproduction.md, "Issue 45"): the fifth arm
(the bottleneck's initialisation, `factorised_init`) runs only when none of arms (a)-(d) counts, each judged by the
registered rule on 8 seeds a side (a choice counts when its interval against its base lies above 0.5).

Re-makes the mechanism report of EXPERIMENT_FOLDER's runs into a temporary folder with the spec's report section
(the one `make_report.sh mechanism-pilot` uses), reads its pairs.csv and exits 0 when (e) is due, 1 when an arm
counts (the variant is next, by hand: its spec names the counted choices), 2 when an arm has not its 8 seeds a side.

    python docs/reports/issue45/arm_e_due.py /work/exp/mechanism-pilot [--adarl PATH/TO/adarl] [--spec SPEC]
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import tempfile
from pathlib import Path

from adarl.experiments.execute import run_is_finished

HERE = Path(__file__).resolve()
REPO = HERE.parents[3]
# (arm, its base): the four "counts" decisions
COUNTS = [
    ("adarl_project", "adarl"),
    ("factorised_lr", "factorised_restarts"),
    ("factorised_product", "factorised_restarts"),
    ("factorised_torchrl", "factorised_restarts"),
]


def _interval(row: dict) -> str:
    return f"{float(row['poi']):.2f} [{float(row['poi_lo']):.2f}, {float(row['poi_hi']):.2f}]"


def decide(pairs_csv: Path) -> tuple[int, str]:
    rows = {(r["a"], r["b"]): r for r in csv.DictReader(pairs_csv.open())}
    missing = [f"{a} vs {b}" for a, b in COUNTS if (a, b) not in rows]
    if missing:
        return 2, f"pairs not in the report: {', '.join(missing)}"
    short = [
        f"{a} ({rows[a, b]['n_a']} vs {rows[a, b]['n_b']})"
        for a, b in COUNTS
        if min(int(rows[a, b]["n_a"]), int(rows[a, b]["n_b"])) < 8
    ]
    if short:
        return 2, f"undecided, fewer than 8 seeds a side: {', '.join(short)}"
    counted = [f"{a} (P = {_interval(rows[a, b])})" for a, b in COUNTS if float(rows[a, b]["poi_lo"]) > 0.5]
    if counted:
        return 1, f"counts: {', '.join(counted)}: arm (e) is not run; AdaRL with the counted choices is next"
    return 0, "none of arms (a)-(d) counts: arm (e) is due"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", type=Path, help="the mechanism arms' experiment folder (its run folders)")
    ap.add_argument("--adarl", default=str(Path(sys.executable).with_name("adarl")), help="the adarl command to run")
    ap.add_argument("--spec", type=Path, default=REPO / "recipes" / "experiments" / "mechanism.yaml")
    args = ap.parse_args(argv)
    # every finished run folder by name (as the committed report reads its runs/): the experiment folder's
    # experiment.json lists only the runs its last call planned, not the bases copied in
    runs = sorted(str(d) for d in args.experiment.glob("env=*") if d.is_dir() and run_is_finished(d))
    with tempfile.TemporaryDirectory() as out:
        cmd = [
            args.adarl,
            "report",
            *runs,
            "--spec",
            str(args.spec),
            "--set",
            "formats=[png]",
            "-o",
            out,
        ]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        code, why = decide(Path(out) / "pairs.csv")
    print(f"arm (e): {why}")
    return code


if __name__ == "__main__":
    sys.exit(main())
