#!/usr/bin/env bash
# Session 30: second training draws (train.seed = 1) of GUR's recipe and of SE's, on the data
# that ship, each evaluated on the same 250 held-out episodes; held-out keyframes last.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s30
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
for arm in gur1 se1; do
  run=runs/s1/$arm
  s=$(date +%s)
  if [ -d $run/checkpoints ]; then $bin train --data $data --out $run --resume --steps 14000
  else $bin train --data $data --out $run --config runs/s1/$arm.toml --steps 14000; fi
  echo "$arm TRAIN WALL $(( $(date +%s) - s )) $(date)"
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $run --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
  echo "$arm ALL WALL $(( $(date +%s) - s )) $(date)"
done
$bin bench compare runs/s1/gur1/success.results.json runs/gu/gur/success.results.json --json > runs/s1/gur1-vs-gur.json
$bin bench compare runs/s1/se1/success.results.json runs/s1/gur1/success.results.json --json > runs/s1/se1-vs-gur1.json
$bin bench compare runs/s1/se1/success.results.json runs/se/se/success.results.json --json > runs/s1/se1-vs-se.json
echo "COMPARES DONE $(date)"
for arm in gur1 se1; do
  $bin bench heldout --checkpoint runs/s1/$arm --data $held --train-data $data --json > runs/s1/$arm/heldout.json
done
echo "HELDOUT DONE $(date)"
