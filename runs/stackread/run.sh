#!/usr/bin/env bash
# Session 30 readout: every stack_blocks held-out episode of a checkpoint, closed loop, with its keyframes.
set -u
cd /work/main
ck=$1; name=$2; pol=${3:-flowram}
mkdir -p runs/stackread/$name
for s in $(seq 1000 1049); do
  [ -s runs/stackread/$name/$s.json ] && continue
  /tmp/flowram-s30c run --task stack_blocks --policy $pol $( [ $pol = flowram ] && echo --checkpoint $ck ) --seed $s --json > runs/stackread/$name/$s.json.tmp 2>/dev/null && mv runs/stackread/$name/$s.json.tmp runs/stackread/$name/$s.json
done
echo DONE
