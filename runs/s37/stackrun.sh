#!/usr/bin/env bash
# Session 37 readout: PB5's stack_blocks episodes (seeds 1000-1049) one by one, closed loop, with keyframes and end layout
# (session 35's binary and profile, lock-step: the outcomes are runs/s36/pb5-here's)
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
out=runs/s37/stackrun; mkdir -p $out
for s in $(seq 1000 1049); do
  [ -s $out/$s.json ] && continue
  /tmp/flowram-s36 run --task stack_blocks --policy flowram --seed $s --max-keyframes 25 --json > $out/$s.json.tmp 2>/dev/null && mv $out/$s.json.tmp $out/$s.json
done
echo STACKRUN DONE
