#!/usr/bin/env bash
# Arm PW2 step 2 (pre-registered): --pointer-posterior-width 0.08 on GUR's and GUR1's weights,
# all five tasks, the seeds and sampling of POST / POST1; then the paired comparisons.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s31
for arm in gur:runs/gu/gur:post gur1:runs/s1/gur1:post1; do
  IFS=: read name ck base <<< "$arm"
  run=runs/pw/$name
  mkdir -p $run
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $ck --pointer-posterior-width 0.08 --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
  $bin bench compare $run/success.results.json runs/$base/success.results.json --json > $run/compare-$base.json
  echo "$name DONE $(date)"
done
