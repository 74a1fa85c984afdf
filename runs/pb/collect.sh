#!/usr/bin/env bash
# Session 35: push_buttons expert version 2 (lime rings): re-collect its 300 demonstrations and
# the held-out 10, as scripts/train-tasks.sh would on a fresh machine.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s35
dir=runs/data/push_buttons-300-perturbed-0.03
for i in 0 1; do
  rm -rf "$dir.s$i"
  "$bin" collect --task push_buttons --episodes 300 --seed 0 --out "$dir.s$i" --shard-index $i --shard-count 2 \
    --perturb-sigma 0.03 --perturb-probability 1 > "$dir.s$i.log" 2>&1 &
done
wait
"$bin" merge "$dir.s0" "$dir.s1" --out "$dir"
rm -rf "$dir.s0" "$dir.s1" "$dir.s0.log" "$dir.s1.log"
"$bin" collect --task push_buttons --episodes 10 --seed 1000 --out runs/data/held_push_buttons
echo collected
