#!/usr/bin/env bash
# Session 37: the readout's context for seeds 1000-1049: idle layouts and the expert on the count-4 variation
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
bin=/tmp/flowram-s36
mkdir -p runs/stackread/expert4 runs/stackread/idle
for s in $(seq 1000 1049); do
  [ -s runs/stackread/idle/$s.json ] || { $bin run --task stack_blocks --policy idle --seed $s --max-keyframes 1 --json > runs/stackread/idle/$s.json.tmp 2>/dev/null && mv runs/stackread/idle/$s.json.tmp runs/stackread/idle/$s.json; }
  [ -s runs/stackread/expert4/$s.json ] && continue
  v=$(( (s % 60) / 3 * 3 + 2 ))
  $bin run --task stack_blocks --policy expert --seed $s --variation $v --json > runs/stackread/expert4/$s.json.tmp 2>/dev/null && mv runs/stackread/expert4/$s.json.tmp runs/stackread/expert4/$s.json
done
echo CTX DONE
