#!/usr/bin/env bash
# Session 42: what runs/stackread/later.py reads, made on this machine: the starting layouts of
# held-out stack_blocks seeds 1000-1009 and 1070-1099 (idle runs) and the held-out episodes of
# seeds 1070-1099 (held_stack_blocks holds 1000-1009).
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s42}
for s in $(seq 1000 1009); do
  [ -s runs/stackread/idle/$s.json ] || $bin run --task stack_blocks --policy idle --seed $s --json > runs/stackread/idle/$s.json 2>/dev/null
done
for s in $(seq 1070 1099); do
  [ -s runs/stackread/idle1070/$s.json ] || $bin run --task stack_blocks --policy idle --seed $s --json > runs/stackread/idle1070/$s.json 2>/dev/null
done
[ -f runs/data/held_stack_blocks_1070/index.json ] || $bin collect --task stack_blocks --episodes 30 --seed 1070 --out runs/data/held_stack_blocks_1070
echo PREP DONE
