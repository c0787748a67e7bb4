#!/usr/bin/env bash
# Humanoid's row amendment (docs/reproduction.md): a short baselines/humanoid_sparse run (seed 0, 6000 frames: 5000
# fused updates through the sparse layer, 3 evaluations, a checkpoint at the end) from the worktree wt-r (6f73355,
# topk's selection) and from wt-h (the commit humanoid_commit names, numpy's), one after the other; then same_layer_check.py compares them.
set -eu
CHECK=$(cd "$(dirname "$0")" && pwd)/same_layer_check.py
EXP=${ISSUE45_EXP:-/work/exp}
OUT=${1:-/tmp/same_layer_check}
mkdir -p $OUT
cd $OUT  # not a checkout: each worktree's installed adarl, never a source tree on the path
for wt in wt-r wt-h; do
  $EXP/$wt/.venv/bin/adarl run baselines/humanoid_sparse -o $OUT/$wt --overwrite --quiet seed=0 \
    collector.total_frames=6000 collector.init_random_frames=1000 eval.interval=2000 checkpoint.interval=6000
done
$EXP/wt-r/.venv/bin/python "$CHECK" $OUT/wt-r $OUT/wt-h
