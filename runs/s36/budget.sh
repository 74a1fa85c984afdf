#!/usr/bin/env bash
# Session 36 readout (no decision rides on it): the shipped checkpoint (PB5) on stack_blocks
# alone, seeds 1000-1049 and 1050-1099, with a 40-keyframe budget instead of the benchmark's 25,
# to count how many of its stack_blocks failures are the budget (the keyframes each success
# used are in the record).
set -euo pipefail
cd /work/main
bin=target/release/flowram
out=runs/s36/budget
mkdir -p $out
for seed in 1000 1050; do
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint models/policy/pretrained/five-tasks --seed $seed --tasks stack_blocks --episodes 50 --max-keyframes 40 \
      --shard-index $i --shard-count 2 --out $out/success$seed.s$i.results.json > $out/success$seed.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $out/success$seed.s0.results.json $out/success$seed.s1.results.json --out $out/success$seed.results.json --json > $out/success$seed.json
  echo "$seed DONE $(date)"
done
