#!/usr/bin/env bash
# Session 32, arm LA5 (pre-registered in docs/experiments.md): GUR's recipe + language_attention_heads = 4,
# seed 0; 500 episodes (seeds 1000-1049 and 1050-1099 per task) paired with the shipped checkpoint's records.
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s32la
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
arm=${1:-la5}
run=runs/la/$arm
s=$(date +%s)
if [ -d $run/checkpoints ]; then $bin train --data $data --out $run --resume --steps 14000
else $bin train --data $data --out $run --config runs/la/$arm.toml --steps 14000; fi
echo "$arm TRAIN WALL $(( $(date +%s) - s )) $(date)"
for seed in 1000 1050; do
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $run --seed $seed --tasks open_drawer,push_buttons,slide_block,close_jar,stack_blocks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success$seed.s$i.results.json > $run/success$seed.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success$seed.s0.results.json $run/success$seed.s1.results.json --out $run/success$seed.results.json --json > $run/success$seed.json
  echo "$arm $seed DONE $(date)"
done
echo "$arm ALL WALL $(( $(date +%s) - s )) $(date)"
$bin bench heldout --checkpoint $run --data $held --train-data $data --json > $run/heldout.json
$bin bench heldout --checkpoint $run --data runs/data/held_push_sequences,runs/data/held_push_sequences_1070,runs/data/held_push_sequences_1120 --train-data runs/data/push_buttons-300-perturbed-0.03 --json > $run/seq90.json 2>$run/seq90.err
echo "HELDOUT DONE $(date)"
