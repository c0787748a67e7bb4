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
case "$1" in
  mechanism-pilot) spec=mechanism ;;
  # Fig. 3 at 1e6: full-rank SAC's runs join stage 2's, made by issue 34's rule for that folder
  table1-decisive) exec bash docs/reports/issue34/make_report.sh table1-decisive ;;
  # Table 1's rows (Hopper's, then Walker2d's, Ant's, Humanoid's): 8 seeds of AdaRL and full-rank SAC, 5 of each baseline (table1's pairs name arms this
  # row does not run: P(adarl > each arm) is the reference column)
  table1-hopper | table1-walker2d | table1-ant | table1-humanoid) spec=table1 extra=(--set 'pairs=[]'
    --set 'verdict_seeds={adarl: 8, sac_full: 8, parseval: 5, sparse: 5, rnac_ipm: 5, rnac_ds: 5}') ;;
  # Parseval's lambda per env: the paper's selection (highest mean of the three values on seeds 100-101), no verdict
  parseval_lambda-laptop_walker2d | parseval_lambda-laptop_ant | parseval_lambda-laptop_humanoid) spec=parseval_lambda ;;
  *) exit 0 ;;
esac
d=docs/reports/$1
[ -d "$d/runs" ] || exit 0
.venv/bin/adarl report "$d/runs" --spec "recipes/experiments/$spec.yaml" "${extra[@]}" --set "formats=[png]" -o "$d" >/dev/null
echo "$d"
