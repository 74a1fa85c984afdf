#!/usr/bin/env bash
# Session 31, arm PC (pre-registered in docs/experiments.md): GUR's recipe + model.point_colour,
# two training draws (seed 0, 1), each evaluated with the shipped sampling (posterior) on the
# same 250 held-out episodes as POST / POST1; held-out keyframes last.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s31
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
for arm in pc pc1; do
  run=runs/pc/$arm
  s=$(date +%s)
  if [ -d $run/checkpoints ]; then $bin train --data $data --out $run --resume --steps 14000
  else $bin train --data $data --out $run --config runs/pc/$arm.toml --steps 14000; fi
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
$bin bench compare runs/pc/pc/success.results.json runs/post/success.results.json --json > runs/pc/pc-vs-post.json
$bin bench compare runs/pc/pc1/success.results.json runs/post1/success.results.json --json > runs/pc/pc1-vs-post1.json
echo "COMPARES DONE $(date)"
for arm in pc pc1; do
  $bin bench heldout --checkpoint runs/pc/$arm --data $held --train-data $data --json > runs/pc/$arm/heldout.json
done
echo "HELDOUT DONE $(date)"
