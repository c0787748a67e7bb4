#!/usr/bin/env bash
# Issue 34's runs, in the protocol's order, from the worktree at 579fa0b (non-editable install in wt-g/.venv).
# Re-running this script resumes: finished runs are skipped, interrupted ones resumed exactly.
#   queue.sh        stage 1 (complete, committed in docs/reports/table1-pilot), then the rest
#   queue.sh rest   stage 2 and the other claims (what fresh_machine.sh starts on a new machine)
set -u
cd /work/exp
A=/work/exp/wt-g/.venv/bin/adarl
PY=/work/exp/wt-g/.venv/bin/python
SPECS=/work/exp/wt-g/recipes/experiments
export ADARL_RECIPES_PATH=/work/exp/extra_recipes MUJOCO_GL=egl
run() { echo "=== $(date -u +%FT%TZ) $*"; "$@" --workers 2 --no-live --progress 600 || echo "!!! failed: $*"; }

stage1() {
  while pgrep -f "budget pilot_(core|controls)" >/dev/null; do sleep 30; done   # an earlier queue's run, if still running
  run $A experiment $SPECS/table1.yaml --budget pilot_core -o /work/exp/table1-pilot
  [ -f extra_recipes/baselines/hopper_sac_fixed_final.yaml ] || $PY protocol.py fixed-final /work/exp/table1-pilot
  run $A experiment /work/exp/table1_controls.yaml --budget pilot_controls -o /work/exp/table1-pilot-controls
  # amendment of 2026-11-26 (docs/reproduction.md): AdaRL with Eq. 10 alone, 5 seeds, reported beside the pilot
  run $A experiment /work/exp/table1_eq10.yaml --budget pilot_eq10 -o /work/exp/table1-pilot-eq10
  # amendment of 2026-11-26, 07:50 UTC (docs/reproduction.md): AdaRL's factorised layers + restarts, never truncated
  run $A experiment /work/exp/table1_factorised.yaml --budget pilot_factorised -o /work/exp/table1-pilot-factorised
  [ -f table1_decisive.yaml ] || $PY protocol.py strongest /work/exp/table1-pilot /work/exp/table1-pilot-controls
}

rest() {
  run $A experiment /work/exp/table1_decisive.yaml --budget decisive -o /work/exp/table1-decisive
  # Fig. 1 before Table 2 since 2026-11-27: begun in the ends of sessions, its short runs finish a claim soonest
  run $A experiment $SPECS/cartpole_rank_sweep.yaml --budget laptop_scored -o /work/exp/cartpole_rank_sweep-laptop_scored
  run $A experiment $SPECS/table2.yaml --budget laptop -o /work/exp/table2-laptop
  mkdir -p /work/exp/warmstart_ablation-laptop
  for s in 0 1 2 3 4; do  # the refill arm is the pilot's AdaRL (the same resolved recipe): its run, or its small files
    d=/work/exp/warmstart_ablation-laptop/warm_start=refill__seed=$s
    pilot=/work/exp/table1-pilot/env=hopper__algorithm=adarl__seed=$s
    [ -e "$pilot" ] || pilot=/work/main/docs/reports/table1-pilot/runs/env=hopper__algorithm=adarl__seed=$s
    [ -e "$d" ] || cp -a "$pilot" "$d"
  done
  run $A experiment $SPECS/warmstart_ablation.yaml --budget laptop -o /work/exp/warmstart_ablation-laptop
  run $A experiment $SPECS/rank_trajectory.yaml --budget laptop -o /work/exp/rank_trajectory-laptop
  run $A experiment $SPECS/parseval_lambda.yaml --budget laptop -o /work/exp/parseval_lambda-laptop
  # follow-up pre-registered 2026-11-27 06:52 UTC: full-rank SAC under Table 2's high box (joins Table 2's report)
  run $A experiment /work/exp/table2_dense.yaml --budget laptop_dense -o /work/exp/table2-laptop-dense
  echo "=== $(date -u +%FT%TZ) queue done"
}

[ "${1:-all}" = rest ] || stage1
rest
