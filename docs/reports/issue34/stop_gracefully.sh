#!/usr/bin/env bash
# End of a session: stop the experiment driver's runs so that none is lost and the driver starts no other run.
#   stop_gracefully.sh          freeze the driver, SIGTERM its trainers (each checkpoints at its current batch; a
#                               resume needs the same machine: a new one restores only finished runs), wait, kill
#   stop_gracefully.sh --drain  freeze the driver and let its trainers finish their runs (nothing to resume: for a
#                               session whose machine may not come back), then kill the queue, driver and commit loop
case "${1:-}" in
  "" | --drain) ;;
  *) echo "stop_gracefully.sh: unknown argument '$1' (allowed: none, or --drain)" >&2; exit 2 ;;
esac
DRV=$(pgrep -f "adarl experiment /work/exp/" | head -1)
[ -n "$DRV" ] || { echo "no experiment driver"; exit 0; }
kill -STOP "$DRV"
TR=$(pgrep -P "$DRV")
echo "$(date -u +%T) driver $DRV frozen; trainers: $TR"
if [ "${1:-}" = --drain ]; then
  limit=86400
else
  limit=300
  for t in $TR; do kill -TERM "$t"; done
fi
for i in $(seq 1 $limit); do
  alive=0
  for t in $TR; do
    st=$(awk '{print $3}' /proc/$t/stat 2>/dev/null)
    [ -n "$st" ] && [ "$st" != "Z" ] && alive=1
  done
  [ $alive = 0 ] && break
  sleep 1
done
echo "$(date -u +%T) trainers exited after ${i}s"
pkill -KILL -f "queue[0-9]*.sh"; kill -KILL "$DRV"; pkill -f commit_landed.sh
sleep 1; pgrep -af "adarl|queue[0-9]*.sh|commit_landed" | grep -v stop_gracefully || echo "all stopped"
