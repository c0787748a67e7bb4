#!/usr/bin/env bash
# Every 10 minutes: export the finished runs of issue 45's experiments into docs/reports/<name>/runs/ of the main
# checkout (issue 34's export_runs.py: the small files only), re-make the report (make_report.sh) and commit that
# folder alone (git commit --only), so that a lost machine costs only the runs in flight. Table 1's rows are held while
# a pair's verdict is due (tests/test_committed_reports.py); Table 1 across its complete rows is re-made each round.
cd /work/main || exit 1
while true; do
  # report folder:experiment folder (decisive_sac's runs join stage 2's report)
  for pair in mechanism-pilot:mechanism-pilot table1-decisive:table1-decisive_sac table1-hopper:table1-hopper \
      table1-walker2d:table1-walker2d table1-ant:table1-ant table1-humanoid:table1-humanoid \
      parseval_lambda-laptop_walker2d:parseval_lambda-laptop_walker2d parseval_lambda-laptop_ant:parseval_lambda-laptop_ant \
      parseval_lambda-laptop_humanoid:parseval_lambda-laptop_humanoid; do
    name=${pair%%:*}
    src=/work/exp/${pair#*:}
    [ -d "$src" ] || continue
    dest=docs/reports/$name
    new=$(.venv/bin/python docs/reports/issue34/export_runs.py "$src" "$dest")
    wt=wt-t  # the worktree (its commit) the runs were made from (runs.csv names each run's own)
    case "$name" in table1-walker2d | table1-ant) wt=wt-r ;; table1-humanoid) wt=wt-h ;; esac
    if [ "$name" = mechanism-pilot ]; then wt=wt-m; case "$new" in *factorised_init*) wt=wt-e ;; esac; fi
    if [ -n "$new" ] || [ -n "$(git status --porcelain -- "$dest/runs")" ]; then
      bash docs/reports/issue45/make_report.sh "$name" || echo "$(date -u +%FT%TZ) report of $dest failed"
      # A landing that completes a Table-1 pair needs its verdict line in reproduction.md in the same commit series:
      # hold it (uncommitted, retried every round) while the row-verdict test fails, and say so once a round.
      case "$name" in table1-*)
        if ! .venv/bin/python -m pytest -q -x -p no:cacheprovider tests/test_committed_reports.py \
            -k "row_verdicts or parseval_runs_at" > /tmp/commit_landed_guard.log 2>&1; then
          echo "$(date -u +%FT%TZ) HELD $name (its pair's verdict line is due; see /tmp/commit_landed_guard.log): $(echo $new | tr '\n' ' ')"
          continue
        fi ;;
      esac
      git add "$dest" && git commit -q -m "Issue 45 runs landed ($name; the queue runs at $(git -C /work/exp/$wt rev-parse --short HEAD), runs copied in by fresh_machine.sh keep their own commit, named in runs.csv and the report): $(echo $new | tr '\n' ' ')" --only -- "$dest" \
        && echo "$(date -u +%FT%TZ) committed $name: $new"
    fi
  done
  # Table 1 across its complete rows (make_report.sh table1): re-made each round, committed only when it changed (a
  # row completed), held like a row while the committed-report tests of Table 1 fail
  if bash docs/reports/issue45/make_report.sh table1 > /dev/null && [ -n "$(git status --porcelain -- docs/reports/table1)" ]; then
    if .venv/bin/python -m pytest -q -x -p no:cacheprovider tests/test_committed_reports.py -k "table1s_" \
        > /tmp/commit_landed_guard.log 2>&1; then
      git add docs/reports/table1 && git commit -q -m "Issue 45: Table 1 across its complete rows re-made ($(tr '\n' ' ' < docs/reports/table1/rows.txt))" --only -- docs/reports/table1 \
        && echo "$(date -u +%FT%TZ) committed table1: $(tr '\n' ' ' < docs/reports/table1/rows.txt)"
    else
      echo "$(date -u +%FT%TZ) HELD table1 (see /tmp/commit_landed_guard.log)"
    fi
  fi
  sleep 600
done
