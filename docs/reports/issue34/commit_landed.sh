#!/usr/bin/env bash
# Every 10 minutes: export the finished runs of issue 34's experiments into docs/reports/<name>/runs/ of the main
# checkout and commit those paths alone (git commit --only), so that a lost machine costs only the runs in flight.
cd /work/main || exit 1
while true; do
  for pair in table1-pilot table1-pilot-controls:table1-pilot table1-pilot-eq10:table1-pilot table1-decisive table2-laptop warmstart_ablation-laptop \
              rank_trajectory-laptop cartpole_rank_sweep-laptop_scored parseval_lambda-laptop; do
    src=/work/exp/${pair%%:*}
    [ -d "$src" ] || continue
    dest=docs/reports/${pair##*:}
    new=$(.venv/bin/python docs/reports/issue34/export_runs.py "$src" "$dest")
    if [ -n "$new" ]; then
      git add "$dest/runs" && git commit -q -m "Issue 34 runs landed ($pair, runs at 579fa0b): $(echo $new | tr '\n' ' ')" --only -- "$dest/runs" \
        && echo "$(date -u +%FT%TZ) committed $pair: $new"
    fi
  done
  sleep 600
done
