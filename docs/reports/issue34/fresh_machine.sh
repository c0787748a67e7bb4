#!/usr/bin/env bash
# Issue 34 at the start of a session, on a new machine without /work/exp (its checkpoints are lost, the committed
# small files are not) or on the last session's, whose /work/exp survived (then only what is missing is made, and
# the runs in flight resume from their checkpoints). Builds the worktree at 579fa0b with its own non-editable install, restores every committed
# finished run into its experiment folder (a run folder with summary.json + recipe.yaml counts as finished, so the
# driver skips it), then starts `queue.sh rest` and the commit loop, both at nice 10. Run from the main checkout,
# after `make install`:
#   bash docs/reports/issue34/fresh_machine.sh
#   bash docs/reports/issue34/fresh_machine.sh --restore-only    # everything but starting the queue and the loop
set -eu
MAIN=$(pwd)
EXP=${ISSUE34_EXP:-/work/exp}   # queue.sh and the commit loop read /work/exp: override only to check a restore
I=$MAIN/docs/reports/issue34
echo 0 > /proc/sys/kernel/sched_autogroup_enabled 2>/dev/null || echo "could not turn sched_autogroup off"
mkdir -p $EXP
[ -d $EXP/wt-g ] || git worktree add $EXP/wt-g 579fa0b
if [ ! -x $EXP/wt-g/.venv/bin/adarl ]; then
  python3 -m venv $EXP/wt-g/.venv
  $EXP/wt-g/.venv/bin/pip install -q --upgrade pip
  $EXP/wt-g/.venv/bin/pip install -q torch==2.13.0
  (cd $EXP/wt-g && .venv/bin/pip install -q -c constraints.txt .)
fi
cp -n $I/table1_decisive.yaml $I/table1_controls.yaml $I/table1_eq10.yaml $I/table1_factorised.yaml \
  $I/protocol.py $I/strongest_control.json $I/table2_dense.yaml $EXP/
# the experiments of `queue.sh rest` whose finished runs are committed (docs/reports/<folder>/runs)
for name in table1-decisive table2-laptop warmstart_ablation-laptop rank_trajectory-laptop \
            cartpole_rank_sweep-laptop_scored parseval_lambda-laptop; do
  src=$MAIN/docs/reports/$name/runs
  [ -d "$src" ] || continue
  mkdir -p $EXP/$name
  for run in "$src"/*/; do
    into=$EXP/$name
    case "$(basename "$run")" in *scope=sac_full*) into=$EXP/table2-laptop-dense; mkdir -p "$into" ;; esac  # the follow-up's
    [ -e "$into/$(basename "$run")" ] || cp -a "$run" "$into/"
  done
  echo "restored $(ls "$src" | wc -l) runs of $name"
done
[ "${1:-}" = --restore-only ] && exit 0
if pgrep -f "adarl experiment $EXP/" >/dev/null || pgrep -f "queue[0-9]*.sh" >/dev/null; then
  echo "an experiment driver or queue runs already: not starting another (stop it first: stop_gracefully.sh)"
else
  cp $I/queue.sh $EXP/queue.sh   # the committed queue, also over a surviving folder's older copy (none runs it now)
  cd $EXP && setsid nohup nice -n 10 bash ./queue.sh rest >> queue.log 2>&1 < /dev/null &
  echo "queue started (log: $EXP/queue.log)"
fi
if pgrep -f commit_landed.sh >/dev/null; then
  echo "the commit loop runs already"
else
  cd $MAIN && setsid nohup nice -n 10 bash docs/reports/issue34/commit_landed.sh >> $EXP/commit_landed.log 2>&1 < /dev/null &
  echo "commit loop started (log: $EXP/commit_landed.log)"
fi
