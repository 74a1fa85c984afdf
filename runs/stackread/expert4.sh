#!/usr/bin/env bash
# The expert with the count-4 variation of each seed's colour: the same layout, all four target blocks in order.
set -u
cd /work/main
mkdir -p runs/stackread/expert4
for s in $(seq 1000 1049); do
  [ -s runs/stackread/expert4/$s.json ] && continue
  v=$(( (s % 60) / 3 * 3 + 2 ))
  /tmp/flowram-s30 run --task stack_blocks --policy expert --seed $s --variation $v --json > runs/stackread/expert4/$s.json.tmp 2>/dev/null && mv runs/stackread/expert4/$s.json.tmp runs/stackread/expert4/$s.json
done
echo DONE
