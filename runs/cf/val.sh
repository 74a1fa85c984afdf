#!/usr/bin/env bash
# Session 34: choosing CF5's guidance w on validation seeds 2000-2029 per task (pre-registered).
# usage: runs/cf/val.sh ARM W [W ...]
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s34b
arm=$1; shift
run=runs/cf/$arm
for w in "$@"; do
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $run --seed 2000 --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 30 --max-keyframes 25 \
      --pointer-guidance $w --shard-index $i --shard-count 2 --out $run/val2000-w$w.s$i.results.json > $run/val2000-w$w.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/val2000-w$w.s0.results.json $run/val2000-w$w.s1.results.json --out $run/val2000-w$w.results.json --json > $run/val2000-w$w.json
  echo "$arm w=$w VAL DONE $(date)"
done
