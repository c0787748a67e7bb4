#!/usr/bin/env bash
# Issue 45 at the start of a session: on a new machine (no /work/exp) or on the last session's (its /work/exp kept:
# only what is missing is made, and the runs in flight resume from their checkpoints). Builds the worktree at 862724f
# with its own non-editable install; puts the pilot's committed base runs (adarl, sac_restarts: the same resolved
# recipes, issue 34's stage 1) and every committed finished run of issue 45 into the experiment folder (a run folder
# with summary.json + recipe.yaml counts as finished: the driver skips it); starts queue.sh and the commit loop at
# nice 10. Run from the main checkout after `make install`:
#   bash docs/reports/issue45/fresh_machine.sh [--restore-only]
set -eu
MAIN=$(pwd)
EXP=${ISSUE45_EXP:-/work/exp}
I=$MAIN/docs/reports/issue45
echo 0 > /proc/sys/kernel/sched_autogroup_enabled 2>/dev/null || echo "could not turn sched_autogroup off"
mkdir -p $EXP
worktree() {  # worktree NAME COMMIT: $EXP/NAME at COMMIT with its own non-editable install (made once)
  [ -d $EXP/$1 ] || git worktree add $EXP/$1 $2
  if [ ! -x $EXP/$1/.venv/bin/adarl ]; then
    python3 -m venv $EXP/$1/.venv
    $EXP/$1/.venv/bin/pip install -q --upgrade pip
    $EXP/$1/.venv/bin/pip install -q torch==2.13.0
    (cd $EXP/$1 && .venv/bin/pip install -q -c constraints.txt .)
  fi
}
worktree wt-m 862724f
into=$EXP/mechanism-pilot
mkdir -p $into
for arm in adarl sac_restarts; do
  for s in 0 1 2 3 4 5 6 7; do
    run=env=hopper__algorithm=${arm}__seed=$s
    [ -e "$into/$run" ] || cp -a "$MAIN/docs/reports/table1-pilot/runs/$run" "$into/"
  done
done
# amendment (docs/reproduction.md, "Issue 45"): factorised_restarts seeds 2-4 are the pilot's (seeds 0 and 1 re-ran
# identical over all 15 evaluations); seeds 0, 1 and 5-7 ran at 862724f
for s in 2 3 4; do
  run=env=hopper__algorithm=factorised_restarts__seed=$s
  [ -e "$into/$run" ] || cp -a "$MAIN/docs/reports/table1-pilot/runs/$run" "$into/"
done
if [ -d "$MAIN/docs/reports/mechanism-pilot/runs" ]; then
  for run in "$MAIN"/docs/reports/mechanism-pilot/runs/*/; do
    [ -e "$into/$(basename "$run")" ] || cp -a "$run" "$into/"
  done
fi
echo "restored $(ls -d $into/env=* | wc -l) runs into $into"
# the experiments after the mechanism arms run from the worktree wt-t at WT_T (queue.sh)
WT_T=${ISSUE45_WT_T:-fa38c5c}
worktree wt-t $WT_T
# arm (e) (the bottleneck's initialisation, run only when none of (a)-(d) counts) from the worktree wt-e at WT_E: the
# commit that added its init scheme, spec budget and amendment (cc50c7f) with arm_e_due.py fixed (f6676ac)
WT_E=${ISSUE45_WT_E:-f6676ac}
worktree wt-e $WT_E
# Table 1's Walker2d, Ant and Humanoid rows run from the worktree wt-r at the commit rows_commit names (written once
# the selected lambdas are in table1.yaml; absent before: no wt-r, and queue.sh says the rows wait)
WT_R=${ISSUE45_WT_R:-$(cat $I/rows_commit 2>/dev/null || true)}
[ -n "$WT_R" ] && worktree wt-r $WT_R
# Humanoid's row runs from the worktree wt-h at the commit humanoid_commit names (rows_commit plus the sparse layer's
# numpy selection alone; the amendment in docs/reproduction.md)
WT_H=${ISSUE45_WT_H:-$(cat $I/humanoid_commit 2>/dev/null || true)}
[ -n "$WT_H" ] && worktree wt-h $WT_H
# each committed run back into its experiment folder (a finished one is skipped by the driver, checked by content)
restore() {  # restore REPORT_FOLDER EXPERIMENT_FOLDER [GLOB]
  [ -d "$MAIN/docs/reports/$1/runs" ] || return 0
  mkdir -p "$EXP/$2"
  for run in "$MAIN"/docs/reports/$1/runs/${3:-*}/; do
    [ -d "$run" ] && { [ -e "$EXP/$2/$(basename "$run")" ] || cp -a "$run" "$EXP/$2/"; }
  done
  return 0
}
restore table1-decisive table1-decisive_sac "*algorithm=sac_full*"
for arm in adarl sac_full parseval; do restore table1-pilot table1-hopper "env=hopper__algorithm=${arm}__seed=*"; done
restore table1-hopper table1-hopper
for env in walker2d ant humanoid; do restore table1-$env table1-$env; done
for env in walker2d ant humanoid; do restore parseval_lambda-laptop_$env parseval_lambda-laptop_$env; done
[ "${1:-}" = --restore-only ] && exit 0
if pgrep -f "adarl experiment" >/dev/null || pgrep -f "queue[0-9]*.sh" >/dev/null; then
  echo "an experiment driver or queue runs already: not starting another"
else
  cp $I/queue.sh $EXP/queue45.sh
  cd $EXP && setsid nohup nice -n 10 bash ./queue45.sh >> queue45.log 2>&1 < /dev/null &
  echo "queue started (log: $EXP/queue45.log)"
fi
if pgrep -f issue45/commit_landed.sh >/dev/null; then
  echo "the commit loop runs already"
else
  cd $MAIN && setsid nohup nice -n 10 bash docs/reports/issue45/commit_landed.sh >> $EXP/commit_landed45.log 2>&1 < /dev/null &
  echo "commit loop started (log: $EXP/commit_landed45.log)"
fi
