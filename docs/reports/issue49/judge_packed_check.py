"""Issue 49's packed check, judged by its protocol (docs/performance.md, "Packed seeds", written before its runs).

8 Hopper seeds of the pilot's AdaRL arm trained as one pack (`adarl experiment table1 --budget pilot_adarl --pack 8`)
against the pilot's 8 committed solo runs (docs/reports/table1-pilot): each packed run must be made from the solo
run's recipe (checked by content) and record its pack; score = the mean of the last three nominal evaluations (the
pilot's rule); P(packed > solo) with the project's stratified bootstrap (95%); a difference shown (the interval
excludes 0.5) is a defect to find before packing is used for results; otherwise "no difference shown" (inconclusive
about differences smaller than 8 seeds a side can see; the per-update equality tests are the evidence of sameness).

    python docs/reports/issue49/judge_packed_check.py PACKED_EXPERIMENT_FOLDER [-o docs/reports/issue49/packed_check]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from adarl.experiments.report._runs import collect_runs
from adarl.experiments.report._sections import verdict
from adarl.experiments.report.stats import poi_estimate
from adarl.runtime.fingerprint import differences
from adarl.runtime.run_folder.run_dir import RunDir

SOLO = Path(__file__).resolve().parents[1] / "table1-pilot" / "runs"
SEEDS = list(range(8))
SCORE_LAST = 3


def _adarl(folder) -> dict[int, object]:
    runs, _ = collect_runs([folder])
    return {r.seed: r for r in runs if r.axes.get("algorithm") == "adarl" and r.axes.get("env") == "hopper"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("packed", type=Path)
    ap.add_argument("-o", "--output", type=Path, default=Path(__file__).resolve().parent / "packed_check")
    args = ap.parse_args(argv)
    solo, packed = _adarl(SOLO), _adarl(args.packed)
    if sorted(solo) != SEEDS or sorted(packed) != SEEDS:
        sys.exit(f"needs seeds {SEEDS} on both sides: solo {sorted(solo)}, packed {sorted(packed)}")
    rows = []
    for s in SEEDS:
        diff = differences(packed[s].path, RunDir(solo[s].path).load_recipe(), theirs="packed", ours="solo")
        if diff:
            sys.exit(f"seed {s}: the packed run is not made from the solo run's recipe: {'; '.join(diff)}")
        summary = json.loads((packed[s].path / "summary.json").read_text())
        if len(summary.get("packed_with") or []) != len(SEEDS):
            sys.exit(f"seed {s}: {packed[s].path} was not trained in a pack of {len(SEEDS)} (packed_with)")
        rows.append({"seed": s, "solo": solo[s].score(SCORE_LAST), "packed": packed[s].score(SCORE_LAST)})
    poi = poi_estimate([r["packed"] for r in rows], [r["solo"] for r in rows])
    said = verdict(poi, "packed", "solo", (8, 8), 8)
    result = {
        "protocol": "docs/performance.md, 'Packed seeds': the packed check",
        "score": f"mean of the last {SCORE_LAST} nominal evaluations",
        "seeds": rows,
        "poi_packed_over_solo": {"point": poi[0], "low": poi[1], "high": poi[2]},
        "verdict": said,
        "packed_folder": str(args.packed),
    }
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        "# Issue 49's packed check: 8 packed Hopper seeds against the pilot's 8 solo runs",
        "",
        f"P(packed > solo) = {poi[0]:.2f} [{poi[1]:.2f}, {poi[2]:.2f}]: **{said}**",
        "",
        "| seed | solo score | packed score |",
        "|---|---|---|",
        *(f"| {r['seed']} | {r['solo']:.1f} | {r['packed']:.1f} |" for r in rows),
    ]
    (args.output / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
