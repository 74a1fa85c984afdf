#!/usr/bin/env bash
# Arm POST step 2 (pre-registered): GUR's weights with --pointer-posterior, all five tasks, the
# seeds and sampling of GUR's record; then the paired comparison and the held-out keyframes.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s30c
run=runs/post
pids=()
for i in 0 1; do
  $bin bench success --checkpoint runs/gu/gur --pointer-posterior --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
    --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait $p; done
$bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
$bin bench compare $run/success.results.json runs/gu/gur/success.results.json --json > $run/compare-gur.json
echo "SUCCESS DONE $(date)"
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
$bin bench heldout --checkpoint runs/gu/gur --pointer-posterior --data $held --train-data $data --json > $run/heldout.json
echo "HELDOUT DONE $(date)"
