#!/usr/bin/env bash
# Session 36 (from runs/pb/confirm.sh): a checkpoint on seeds 1000-1049 and 1050-1099 per task (TASKS, default the five),
# then the teacher-forced held-out benchmark (pre-registered; arms PB5 / PB5-1, and LP5 / LP5-1
# on the corrected push_buttons with TASKS=push_buttons HELDOUT=0).
# usage: runs/pb/confirm.sh CHECKPOINT OUTDIR
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s36
tasks=${TASKS:-open_drawer,push_buttons,slide_block,close_jar,stack_blocks}
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
ckpt=$1; out=$2
mkdir -p $out
s=$(date +%s)
for seed in ${SEEDS:-1000 1050}; do
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $ckpt --seed $seed --tasks $tasks --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $out/success$seed.s$i.results.json > $out/success$seed.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $out/success$seed.s0.results.json $out/success$seed.s1.results.json --out $out/success$seed.results.json --json > $out/success$seed.json
  echo "$out $seed DONE $(date)"
done
echo "$out ALL WALL $(( $(date +%s) - s )) $(date)"
if [ "${HELDOUT:-1}" = 1 ]; then
  $bin bench heldout --checkpoint $ckpt --data $held --train-data $data --json > $out/heldout.json
  echo "$out HELDOUT DONE $(date)"
fi
