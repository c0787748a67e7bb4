#!/usr/bin/env bash
# Re-make one of issue 45's committed reports from its committed runs/ by the pre-registered rule (docs/reproduction.md,
# "Issue 45"): the report section of the spec its runs were planned from (score = mean of the last three nominal
# evaluations, per-env plateau, the reference and pairs), with no verdict before each arm has its planned seeds
# (verdict_seeds). Prints nothing for a folder it does not make (commit_landed.sh calls it for every folder).
#   bash docs/reports/issue45/make_report.sh mechanism-pilot
# Committed reports keep PNG figures alone (formats=[png]): a PDF and an SVG of every figure, re-made at each landing,
# would grow the repository by megabytes; `adarl report` over the committed runs/ writes them where wanted.
set -eu
extra=()
# Table 1's planned seeds per arm (the protocol's): a row's verdicts wait for them, and the aggregate takes a row only
# once it has them all
TABLE1_SEEDS='{adarl: 8, sac_full: 8, parseval: 5, sparse: 5, rnac_ipm: 5, rnac_ds: 5}'
case "$1" in
  mechanism-pilot) spec=mechanism ;;
  # Fig. 3 at 1e6: full-rank SAC's runs join stage 2's, made by issue 34's rule for that folder
  table1-decisive) exec bash docs/reports/issue34/make_report.sh table1-decisive ;;
  # Table 1's rows (Hopper's, then Walker2d's, Ant's, Humanoid's): 8 seeds of AdaRL and full-rank SAC, 5 of each
  # baseline (table1's pairs name arms this row does not run: P(adarl > each arm) is the reference column)
  table1-hopper | table1-walker2d | table1-ant | table1-humanoid) spec=table1 extra=(--set 'pairs=[]'
    --set "verdict_seeds=$TABLE1_SEEDS") ;;
  # Table 1 across its rows (rliable's normalised aggregate over the four envs: described, no rule): the complete rows
  # alone (every arm with its planned seeds), so that no method's aggregate mixes envs another method lacks
  table1)
    rows=()
    for env in hopper walker2d ant humanoid; do
      t=docs/reports/table1-$env/paper_table.csv
      [ -f "$t" ] && .venv/bin/python - "$t" "$env" "$TABLE1_SEEDS" <<'PY' && rows+=("docs/reports/table1-$env/runs")
import csv, sys
import yaml
planned = yaml.safe_load(sys.argv[3])
# a row's paper_table.csv has a line for every env of Table 1 (0 seeds where it ran none): its own env's count
n = {r["algorithm"]: int(r["n_seeds"]) for r in csv.DictReader(open(sys.argv[1])) if r["env"] == sys.argv[2]}
sys.exit(0 if all(n.get(a, 0) >= k for a, k in planned.items()) else 1)
PY
    done
    [ ${#rows[@]} -gt 0 ] || exit 0
    # a complete row's runs are final: the same rows make the same report (FORCE=1 re-makes it anyway)
    if [ "${FORCE:-0}" != 1 ] && [ "$(printf '%s\n' "${rows[@]}")" = "$(cat docs/reports/table1/rows.txt 2>/dev/null)" ]; then
      exit 0
    fi
    mkdir -p docs/reports/table1
    .venv/bin/adarl report "${rows[@]}" --spec recipes/experiments/table1.yaml --set 'pairs=[]' \
      --set "verdict_seeds=$TABLE1_SEEDS" --set "formats=[png]" -o docs/reports/table1 >/dev/null
    printf '%s\n' "${rows[@]}" > docs/reports/table1/rows.txt
    echo docs/reports/table1
    exit 0 ;;
  # Parseval's lambda per env: the paper's selection (highest mean of the three values on seeds 100-101), no verdict
  parseval_lambda-laptop_walker2d | parseval_lambda-laptop_ant | parseval_lambda-laptop_humanoid) spec=parseval_lambda ;;
  *) exit 0 ;;
esac
d=docs/reports/$1
[ -d "$d/runs" ] || exit 0
.venv/bin/adarl report "$d/runs" --spec "recipes/experiments/$spec.yaml" "${extra[@]}" --set "formats=[png]" -o "$d" >/dev/null
echo "$d"
