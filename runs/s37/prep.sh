#!/usr/bin/env bash
# Session 37: held-out stack_blocks episodes (seeds 1000-1009, 1070-1099) and their idle layouts, for the pick proxy
set -u
cd /work/main
bin=target/release/flowram
[ -f runs/data/held_stack_blocks/index.json ] || $bin collect --task stack_blocks --episodes 10 --seed 1000 --out runs/data/held_stack_blocks
[ -f runs/data/held_stack_blocks_1070/index.json ] || $bin collect --task stack_blocks --episodes 30 --seed 1070 --out runs/data/held_stack_blocks_1070
mkdir -p runs/stackread/idle runs/stackread/idle1070
for s in $(seq 1000 1009) $(seq 1070 1099); do
  d=runs/stackread/idle; [ $s -ge 1050 ] && d=runs/stackread/idle1070
  [ -s $d/$s.json ] && continue
  $bin run --task stack_blocks --policy idle --seed $s --max-keyframes 1 --json > $d/$s.json.tmp 2>/dev/null && mv $d/$s.json.tmp $d/$s.json
done
echo PREP DONE $(date)
