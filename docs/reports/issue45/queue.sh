#!/usr/bin/env bash
# Issue 45's runs, in the pre-registered order (docs/reproduction.md, "Issue 45": "Order and cost"). The mechanism
# arms run from the worktree at 862724f (wt-m), arm (e) (when due) from the worktree wt-e, everything after them from
# the worktree wt-t (the commits of wt-e and wt-t are the ones fresh_machine.sh names), each with its own
# non-editable install. Re-running this script resumes: finished
# runs are skipped (by content: a folder made from another resolved recipe is "changed", never reused), interrupted
# ones resumed exactly from their checkpoints.
set -u
cd /work/exp
M=/work/exp/wt-m/.venv/bin/adarl
T=/work/exp/wt-t/.venv/bin/adarl
SPECS_M=/work/exp/wt-m/recipes/experiments
SPECS_T=/work/exp/wt-t/recipes/experiments
export MUJOCO_GL=egl
run() { echo "=== $(date -u +%FT%TZ) $*"; "$@" --workers 2 --no-live --progress 600 || echo "!!! failed: $*"; }
# the mechanism arms: 40 runs; the bases adarl and sac_restarts are the pilot's
run $M experiment $SPECS_M/mechanism.yaml --budget pilot -o /work/exp/mechanism-pilot
# arm (e), the bottleneck's initialisation (its amendment in docs/reproduction.md): from the worktree wt-e, only when
# none of arms (a)-(d) counts by the registered rule (arm_e_due.py: exit 0 due, 1 an arm counts, 2 undecided)
E=/work/exp/wt-e/.venv/bin
echo "=== $(date -u +%FT%TZ) is arm (e) due?"
if [ -x $E/adarl ] && $E/python /work/exp/wt-e/docs/reports/issue45/arm_e_due.py /work/exp/mechanism-pilot; then
  run $E/adarl experiment /work/exp/wt-e/recipes/experiments/mechanism.yaml --budget pilot_init -o /work/exp/mechanism-pilot
fi
# Fig. 3 at 1e6: full-rank SAC, 8 seeds, stage 2's budget (its report: docs/reports/table1-decisive)
run $T experiment $SPECS_T/table1.yaml --budget decisive_sac -o /work/exp/table1-decisive_sac
# Table 1's Hopper row: the pilot's AdaRL, SAC and Parseval (copied in by fresh_machine.sh, checked by content) and
# the three missing baselines, 5 seeds each
run $T experiment $SPECS_T/table1.yaml --budget table1_hopper -o /work/exp/table1-hopper
# Parseval's lambda per env (the paper's selection, seeds 100-101), before each row's Parseval arm: the selected
# values go into table1.yaml by a commit before the Walker2d, Ant and Humanoid rows run (a new worktree then)
for env in walker2d ant humanoid; do
  run $T experiment $SPECS_T/parseval_lambda.yaml --budget laptop_$env -o /work/exp/parseval_lambda-laptop_$env
done
echo "=== $(date -u +%FT%TZ) queue done"
