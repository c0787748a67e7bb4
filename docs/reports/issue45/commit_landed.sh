#!/usr/bin/env bash
# Every 10 minutes: export the finished runs of issue 45's experiments into docs/reports/<name>/runs/ of the main
# checkout (issue 34's export_runs.py: the small files only), re-make the report (make_report.sh) and commit that
# folder alone (git commit --only), so that a lost machine costs only the runs in flight.
cd /work/main || exit 1
while true; do
  for name in mechanism-pilot; do
    src=/work/exp/$name
    [ -d "$src" ] || continue
    dest=docs/reports/$name
    new=$(.venv/bin/python docs/reports/issue34/export_runs.py "$src" "$dest")
    if [ -n "$new" ] || [ -n "$(git status --porcelain -- "$dest/runs")" ]; then
      bash docs/reports/issue45/make_report.sh "$name" || echo "$(date -u +%FT%TZ) report of $dest failed"
      git add "$dest" && git commit -q -m "Issue 45 runs landed ($name, runs at 862724f): $(echo $new | tr '\n' ' ')" --only -- "$dest" \
        && echo "$(date -u +%FT%TZ) committed $name: $new"
    fi
  done
  sleep 600
done
