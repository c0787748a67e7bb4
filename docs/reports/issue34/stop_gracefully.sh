#!/usr/bin/env bash
# End of a session: stop issue 34's runs so that each checkpoints at its current batch (the worktree's driver
# would otherwise start the next runs): freeze the driver, SIGTERM its trainers, wait, then kill the rest.
DRV=$(pgrep -f "adarl experiment /work/exp/" | head -1)
[ -n "$DRV" ] || { echo "no experiment driver"; exit 0; }
kill -STOP "$DRV"
TR=$(pgrep -P "$DRV")
echo "driver $DRV frozen; trainers: $TR"
for t in $TR; do kill -TERM "$t"; done
for i in $(seq 1 300); do
  alive=0
  for t in $TR; do
    st=$(awk '{print $3}' /proc/$t/stat 2>/dev/null)
    [ -n "$st" ] && [ "$st" != "Z" ] && alive=1
  done
  [ $alive = 0 ] && break
  sleep 1
done
echo "trainers exited after ${i}s"
pkill -KILL -f "queue[0-9]*.sh"; kill -KILL "$DRV"; pkill -f commit_landed.sh
sleep 1; pgrep -af "adarl|queue[0-9]*.sh|commit_landed" | grep -v stop_gracefully || echo "all stopped"
