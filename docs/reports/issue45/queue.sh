#!/usr/bin/env bash
# Issue 45's runs, in the pre-registered order, from the worktree at 862724f (non-editable install in wt-m/.venv).
# Re-running this script resumes: finished runs are skipped, interrupted ones resumed exactly from their checkpoints.
set -u
cd /work/exp
A=/work/exp/wt-m/.venv/bin/adarl
SPECS=/work/exp/wt-m/recipes/experiments
export MUJOCO_GL=egl
run() { echo "=== $(date -u +%FT%TZ) $*"; "$@" --workers 2 --no-live --progress 600 || echo "!!! failed: $*"; }
# the mechanism arms (docs/reproduction.md, "Issue 45"): 40 runs; the bases adarl and sac_restarts are the pilot's
run $A experiment $SPECS/mechanism.yaml --budget pilot -o /work/exp/mechanism-pilot
echo "=== $(date -u +%FT%TZ) queue done"
