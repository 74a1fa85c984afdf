#!/usr/bin/env bash
# Session 41 (new machine kind C: Intel Xeon, AVX-512): arm SW restarted from nothing with this
# HEAD's binary. 1. the recipe's data (as scripts/train-tasks.sh collects it, timed), 2. SW's
# training (timed, alone), 3. evaluation: runs/s41/eval.sh.
# Resumable: collection skips datasets there, training resumes, bench success skips done episodes.
set -u
cd /work/main
bin=/tmp/flowram-s41
d=runs/data
shards=2
stamp() { echo "[$(date +%H:%M:%S)] $*"; }
collect_sharded() { # TASK N DIR [collect options...]
  local task=$1 n=$2 dir=$3 pids=() parts=() i
  shift 3
  for ((i = 0; i < shards; i++)); do
    rm -rf "$dir.s$i"; parts+=("$dir.s$i")
    $bin collect --task "$task" --episodes "$n" --seed 0 --out "$dir.s$i" --shard-index $i --shard-count $shards "$@" > "$dir.s$i.log" 2>&1 &
    pids+=($!)
  done
  for i in "${!pids[@]}"; do wait "${pids[$i]}" || { echo "collect $task shard $i failed"; exit 1; }; done
  $bin merge "${parts[@]}" --out "$dir"
  for i in "${!parts[@]}"; do rm -rf "${parts[$i]}" "${parts[$i]}.log"; done
}
mkdir -p $d
s=$(date +%s)
for tn in open_drawer:100 push_buttons:300 slide_block:300 close_jar:300 stack_blocks:300; do
  task=${tn%%:*}; n=${tn##*:}
  dir=$d/$task-$n-perturbed-0.03
  [ -f $dir/index.json ] || collect_sharded $task $n $dir --perturb-sigma 0.03 --perturb-probability 1
  [ -f $d/held_$task/index.json ] || $bin collect --task $task --episodes 10 --seed 1000 --out $d/held_$task
  stamp "data $task done"
done
stamp "DATA DONE wall $(( $(date +%s) - s )) s"
data=$d/open_drawer-100-perturbed-0.03,$d/push_buttons-300-perturbed-0.03,$d/slide_block-300-perturbed-0.03,$d/close_jar-300-perturbed-0.03,$d/stack_blocks-300-perturbed-0.03
s=$(date +%s)
if [ -f runs/s41/sw/checkpoints/ema.safetensors ] || [ -d runs/s41/sw/checkpoints ]; then
  $bin train --data $data --out runs/s41/sw --resume
else
  $bin train --data $data --out runs/s41/sw --config runs/s40/sw.toml
fi
stamp "SW TRAIN DONE wall $(( $(date +%s) - s )) s"
# The evaluation: runs/s41/eval.sh (this script's first version evaluated whole tasks per arm;
# it was stopped during training and replaced by paired halves, before any evaluation ran).
