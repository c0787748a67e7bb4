#!/usr/bin/env bash
# Re-make a committed report of issue 34 from its committed runs/ by the pre-registered rule (docs/reproduction.md),
# with the report section of the spec its runs were planned from (the committed runs/ have no experiment.json to
# take it from): score = mean of the last three nominal evaluations, plateau 1500, and the probabilities of
# improvement each rule names (table1: P(adarl > each arm) and its pairs; table2: P(both > each scope); Fig. 9:
# P(refill dips less); Fig. 1: P(rank 8 > rank 4) and P(rank 8 > rank 16)).
# Run from the main checkout:
#   bash docs/reports/issue34/make_report.sh table1-pilot
# Prints nothing for a report this protocol does not make (the loop in commit_landed.sh calls it for every folder).
# verdict_seeds: each spec's planned seeds per arm; while its runs land one by one, a verdict waits for them all.
# Committed reports keep PNG figures alone (formats=[png]): a PDF and an SVG of every figure, re-made at each landing,
# would grow the repository by megabytes; `adarl report` over the committed runs/ writes them where wanted.
set -eu
extra=()
case "$1" in
  table1-pilot) spec=table1 ;;
  # stage 2 runs two arms: P(adarl > parseval) is the reference column, table1's pairs name arms it does not run
  table1-decisive) spec=table1 extra=(--set 'pairs=[]' --set verdict_seeds=8) ;;
  table2-laptop) spec=table2 extra=(--set verdict_seeds=5) ;;
  warmstart_ablation-laptop) spec=warmstart_ablation extra=(--set verdict_seeds=5) ;;
  rank_trajectory-laptop) spec=rank_trajectory ;;
  cartpole_rank_sweep-laptop_scored) spec=cartpole_rank_sweep extra=(--set verdict_seeds=10) ;;
  parseval_lambda-laptop) spec=parseval_lambda ;;
  *) exit 0 ;;
esac
d=docs/reports/$1
[ -d "$d/runs" ] || exit 0
.venv/bin/adarl report "$d/runs" --spec "recipes/experiments/$spec.yaml" "${extra[@]}" --set "formats=[png]" -o "$d" >/dev/null
echo "$d"
