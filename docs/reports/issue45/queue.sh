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
# Table 1's Walker2d, Ant and Humanoid rows (amendment f4d851d: their sparse arm on the fused update): from the
# worktree wt-r at the commit named in docs/reports/issue45/rows_commit (fresh_machine.sh builds it), a row only once
# that commit's table1.yaml gives its budget the selected lambda (value_overrides: {algorithm: {parseval: [...]}})
# Humanoid's row (amendment in the commit that adds humanoid_commit, docs/reproduction.md): from the worktree wt-h at
# the commit docs/reports/issue45/humanoid_commit names (rows_commit plus the sparse layer's numpy selection alone)
for env in walker2d ant humanoid; do
  wt=wt-r
  [ "$env" = humanoid ] && wt=wt-h
  W=/work/exp/$wt/.venv/bin
  # a worktree is made once its commit is written (`fresh_machine.sh --restore-only` builds it beside this running
  # queue): the queue waits for its install, not for a clock
  [ -x $W/adarl ] || echo "=== $(date -u +%FT%TZ) table1_$env waits for the worktree $wt"
  until [ -x $W/adarl ]; do sleep 60; done
  if $W/python - "$env" "$wt" <<'PY'
import sys
from adarl.experiments.spec import load_experiment
budget = load_experiment(f"/work/exp/{sys.argv[2]}/recipes/experiments/table1.yaml").budgets[f"table1_{sys.argv[1]}"]
sys.exit(0 if budget.value_overrides.get("algorithm", {}).get("parseval") else 1)
PY
  then
    run $W/adarl experiment /work/exp/$wt/recipes/experiments/table1.yaml --budget table1_$env -o /work/exp/table1-$env
  else
    echo "=== $(date -u +%FT%TZ) table1_$env waits: its worktree $wt's table1.yaml has no selected lambda for $env"
  fi
done
# Issue 49's packed check (its protocol: docs/performance.md, written before its runs) once Table 1's rows are done:
# one process on one core, from its own worktree wt-p at the commit docs/reports/issue49/pack_commit names
echo "=== $(date -u +%FT%TZ) issue 49's packed check"
(cd /work/main && PACK_COMMIT=$(cat docs/reports/issue49/pack_commit) bash docs/reports/issue49/run_packed_check.sh) \
  || echo "!!! issue 49's packed check failed or landed nothing new"
echo "=== $(date -u +%FT%TZ) queue done"
