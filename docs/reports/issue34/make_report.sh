#!/usr/bin/env bash
# Re-make a committed report of issue 34 from its committed runs/ by the pre-registered rule (docs/reproduction.md):
# table1.yaml's report section: score = mean of the last three nominal evaluations, plateau 1500, P(adarl > each arm)
# and the pairs it names.
# Run from the main checkout:
#   bash docs/reports/issue34/make_report.sh table1-pilot
# Prints nothing for a report this protocol does not make (the loop in commit_landed.sh calls it for every folder).
set -eu
case "$1" in
  table1-pilot|table1-decisive) ;;
  *) exit 0 ;;
esac
d=docs/reports/$1
[ -d "$d/runs" ] || exit 0
# table1.yaml's report section (the committed runs/ have no experiment.json to take it from)
.venv/bin/adarl report "$d/runs" --spec recipes/experiments/table1.yaml -o "$d" >/dev/null
echo "$d"
