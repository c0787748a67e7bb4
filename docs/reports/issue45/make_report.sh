#!/usr/bin/env bash
# Re-make issue 45's committed report from its committed runs/ by the pre-registered rule (docs/reproduction.md,
# "Issue 45"): the report section of recipes/experiments/mechanism.yaml (score = mean of the last three nominal
# evaluations, plateau 1500, reference factorised_restarts, the pre-registered pairs, no verdict before 8 seeds a side).
#   bash docs/reports/issue45/make_report.sh mechanism-pilot
set -eu
case "$1" in
  mechanism-pilot) spec=mechanism ;;
  *) exit 0 ;;
esac
d=docs/reports/$1
[ -d "$d/runs" ] || exit 0
.venv/bin/adarl report "$d/runs" --spec "recipes/experiments/$spec.yaml" -o "$d" >/dev/null
echo "$d"
