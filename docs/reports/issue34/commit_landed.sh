#!/usr/bin/env bash
# Every 10 minutes: export the finished runs of issue 34's experiments into docs/reports/<name>/runs/ of the main
# checkout, re-make the protocol's report there (make_report.sh) and commit that folder alone (git commit --only),
# so that a lost machine costs only the runs in flight. A commit that failed (e.g. a lock) is retried next time.
cd /work/main || exit 1
while true; do
  for pair in table1-pilot table1-pilot-controls:table1-pilot table1-pilot-eq10:table1-pilot \
              table1-pilot-factorised:table1-pilot table1-decisive table2-laptop warmstart_ablation-laptop \
              rank_trajectory-laptop cartpole_rank_sweep-laptop_scored parseval_lambda-laptop \
              table2-laptop-dense:table2-laptop; do
    src=/work/exp/${pair%%:*}
    [ -d "$src" ] || continue
    dest=docs/reports/${pair##*:}
    new=$(.venv/bin/python docs/reports/issue34/export_runs.py "$src" "$dest")
    if [ -n "$new" ] || [ -n "$(git status --porcelain -- "$dest/runs")" ]; then
      # the protocol's reports are re-made with their runs, so that runs/ and runs.csv never disagree in a commit
      bash docs/reports/issue34/make_report.sh "${pair##*:}" || echo "$(date -u +%FT%TZ) report of $dest failed"
      git add "$dest" && git commit -q -m "Issue 34 runs landed ($pair, runs at 579fa0b): $(echo $new | tr '\n' ' ')" --only -- "$dest" \
        && echo "$(date -u +%FT%TZ) committed $pair: $new"
    fi
  done
  sleep 600
done
