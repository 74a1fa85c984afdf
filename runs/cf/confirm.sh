#!/usr/bin/env bash
# Session 34: CF5 / CF5-1 on seeds 1000-1049 and 1050-1099 per task at the chosen guidance w,
# then the teacher-forced held-out benchmark (pre-registered).
# usage: runs/cf/confirm.sh ARM W
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s34b
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
arm=$1; w=$2
run=runs/cf/$arm
s=$(date +%s)
for seed in 1000 1050; do
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $run --seed $seed --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --pointer-guidance $w --shard-index $i --shard-count 2 --out $run/success$seed.s$i.results.json > $run/success$seed.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success$seed.s0.results.json $run/success$seed.s1.results.json --out $run/success$seed.results.json --json > $run/success$seed.json
  echo "$arm $seed DONE $(date)"
done
echo "$arm ALL WALL $(( $(date +%s) - s )) $(date)"
$bin bench heldout --checkpoint $run --data $held --train-data $data --pointer-guidance $w --json > $run/heldout.json
echo "$arm HELDOUT DONE $(date)"
