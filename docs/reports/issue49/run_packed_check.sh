#!/usr/bin/env bash
# Issue 49's packed check (its protocol: docs/performance.md, "Packed seeds", written before its runs). One process,
# one core: the pilot's AdaRL arm, 8 seeds packed, 300k frames (about 2 h here, estimated from the measured 1.86x
# per core). Runs from a worktree at PACK_COMMIT with its own non-editable install, so that edits on main never reach
# it; exports the small files into docs/reports/issue49/packed_check/runs (issue 34's export_runs.py), judges them and
# commits that folder alone. Start it only when a core is free (at most two training processes on 2 cores):
#   bash docs/reports/issue49/run_packed_check.sh            # resumes where a stopped run left off
set -eu
MAIN=$(pwd)
EXP=${ISSUE49_EXP:-/work/exp}
COMMIT=${PACK_COMMIT:?name the commit the check runs at: PACK_COMMIT=<sha> (one with this script)}
WT=$EXP/wt-p
[ -d $WT ] || git worktree add $WT $COMMIT
[ "$(git -C $WT rev-parse HEAD)" = "$(git rev-parse $COMMIT)" ] || { echo "$WT is not at $COMMIT"; exit 1; }
if [ ! -x $WT/.venv/bin/adarl ]; then
  python3 -m venv $WT/.venv
  $WT/.venv/bin/pip install -q --upgrade pip
  $WT/.venv/bin/pip install -q torch==2.13.0
  (cd $WT && .venv/bin/pip install -q -c constraints.txt .)
fi
OUT=$EXP/packed-check
MUJOCO_GL=egl OMP_NUM_THREADS=1 $WT/.venv/bin/adarl experiment $WT/recipes/experiments/table1.yaml \
  --budget pilot_adarl --pack 8 -j 1 -o $OUT --no-live --progress 600 --no-report
DEST=docs/reports/issue49/packed_check
.venv/bin/python docs/reports/issue34/export_runs.py $OUT $DEST
.venv/bin/python docs/reports/issue49/judge_packed_check.py $DEST/runs -o $DEST
git add $DEST && git commit -q --only -m "Issue 49's packed check landed (runs at $COMMIT)" -- $DEST
