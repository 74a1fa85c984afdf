#!/usr/bin/env bash
# Session 31 readout: push_buttons' two- and three-button held-out episodes (seeds 1020-1049),
# closed loop with the shipped checkpoint and with the expert, keyframes kept (run --json).
set -u
cd /work/main
for pol in expert flowram; do
  mkdir -p runs/pushread/$pol
  for s in $(seq 1020 1049); do
    [ -s runs/pushread/$pol/$s.json ] && continue
    /tmp/flowram-s31 run --task push_buttons --policy $pol --seed $s --json > runs/pushread/$pol/$s.json.tmp 2>/dev/null && mv runs/pushread/$pol/$s.json.tmp runs/pushread/$pol/$s.json
  done
done
echo DONE
