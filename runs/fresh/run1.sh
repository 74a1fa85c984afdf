#!/usr/bin/env bash
# Session 31: GUR1 (the second draw) with and without the posterior, on fresh seeds
# 1050-1099 per task; then the paired comparison.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s31
for arm in post1:runs/s1/gur1:--pointer-posterior gur1:runs/s1/gur1:; do
  IFS=: read name ck flag <<< "$arm"
  run=runs/fresh/$name
  mkdir -p $run
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $ck $flag --seed 1050 --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
  echo "$name DONE $(date)"
done
$bin bench compare runs/fresh/post1/success.results.json runs/fresh/gur1/success.results.json --json > runs/fresh/compare1.json
echo "COMPARE DONE $(date)"
