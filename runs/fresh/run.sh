#!/usr/bin/env bash
# Session 31: the shipped checkpoint (posterior) and GUR's weights without it, on fresh seeds
# 1050-1099 per task; then the paired comparison.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s31
for arm in post:models/policy/pretrained/five-tasks gur:runs/gu/gur; do
  IFS=: read name ck <<< "$arm"
  run=runs/fresh/$name
  mkdir -p $run
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $ck --seed 1050 --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
  echo "$name DONE $(date)"
done
$bin bench compare runs/fresh/post/success.results.json runs/fresh/gur/success.results.json --json > runs/fresh/compare.json
echo "COMPARE DONE $(date)"
