#!/usr/bin/env bash
# Makes a multi-task FlowRAM checkpoint from nothing:
#   scripts/train-tasks.sh NAME CONFIG TASK [TASK...]
#  1. expert demonstrations (collected by COLLECT_SHARDS processes side by side, default one per
#     core, then merged): DEMOS (default 100; DEMOS_<task>, e.g. DEMOS_push_buttons=300, for one
#     task) successful episodes of each task from seed 0, with recovery samples when PERTURB_SIGMA
#     is set (metres, `collect --perturb-sigma`, every approach keyframe: probability 1), and 10
#     held-out episodes of each from seed 1000 (plain expert, for `bench heldout`), into runs/data/;
#  2. training with CONFIG into runs/NAME (FLOWRAM_TRAIN_STEPS overrides the config's steps);
#  3. held-out keyframe errors and closed-loop success (EPISODES per task, default 50, seeds
#     1000+, in the same shards) into runs/NAME/{heldout,success}.json and the per-episode record
#     runs/NAME/success.results.json (for `flowram bench compare`).
# Collection is skipped for datasets already there; rerunning continues the training if it was
# killed (`train --resume`). scripts/train-five-tasks.sh and scripts/train-ten-tasks.sh call it
# for the shipped checkpoints.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ $# -lt 3 ]; then
  echo "usage: scripts/train-tasks.sh NAME CONFIG TASK [TASK...]" >&2
  exit 2
fi
name=$1 config=$2
shift 2
tasks=("$@")
scripts/setup.sh
cargo build --release --locked
bin=target/release/flowram
demos="${DEMOS:-100}"
run=runs/$name
data=()
held=()
perturb=()
suffix=
if [ -n "${PERTURB_SIGMA:-}" ]; then
  perturb=(--perturb-sigma "$PERTURB_SIGMA" --perturb-probability 1)
  suffix=-perturbed-$PERTURB_SIGMA
fi
# One `collect` per core (COLLECT_SHARDS, default nproc), each on its own shard of the seeds
# (episode k on shard k mod count), merged into one dataset: the same episodes as one process.
shards="${COLLECT_SHARDS:-$(nproc)}"
mkdir -p runs/data
collect_sharded() { # TASK N DIR [collect options...]
  local task=$1 n=$2 dir=$3 pids=() parts=() i
  shift 3
  if [ "$shards" -le 1 ]; then
    "$bin" collect --task "$task" --episodes "$n" --seed 0 --out "$dir" "$@"
    return
  fi
  for ((i = 0; i < shards; i++)); do
    rm -rf "$dir.s$i"
    parts+=("$dir.s$i")
    "$bin" collect --task "$task" --episodes "$n" --seed 0 --out "$dir.s$i" \
      --shard-index "$i" --shard-count "$shards" "$@" > "$dir.s$i.log" 2>&1 &
    pids+=($!)
  done
  for i in "${!pids[@]}"; do
    wait "${pids[$i]}" || { echo "collect shard $i of $task failed, see $dir.s$i.log" >&2; exit 1; }
  done
  "$bin" merge "${parts[@]}" --out "$dir"
  for i in "${!parts[@]}"; do rm -rf "${parts[$i]}" "${parts[$i]}.log"; done
}
for task in "${tasks[@]}"; do
  count_var=DEMOS_$task
  n=${!count_var:-$demos}
  dir=runs/data/$task-$n$suffix
  [ -f "$dir/index.json" ] || collect_sharded "$task" "$n" "$dir" "${perturb[@]}"
  [ -f "runs/data/held_$task/index.json" ] || "$bin" collect --task "$task" --episodes 10 --seed 1000 --out "runs/data/held_$task"
  data+=("$dir")
  held+=("runs/data/held_$task")
done
data_list=$(IFS=,; echo "${data[*]}")
held_list=$(IFS=,; echo "${held[*]}")
steps=()
[ -z "${FLOWRAM_TRAIN_STEPS:-}" ] || steps=(--steps "$FLOWRAM_TRAIN_STEPS")
if [ -d "$run/checkpoints" ]; then
  "$bin" train --data "$data_list" --out "$run" --resume "${steps[@]}"
else
  "$bin" train --data "$data_list" --out "$run" --config "$config" "${steps[@]}"
fi
"$bin" bench heldout --checkpoint "$run" --data "$held_list" --train-data "$data_list" --json > "$run/heldout.json"
# The evaluation in the same shards (every shard's record resumes if rerun), merged into one table.
task_list=$(IFS=,; echo "${tasks[*]}")
pids=()
parts=()
for ((i = 0; i < shards; i++)); do
  parts+=("$run/success.s$i.results.json")
  "$bin" bench success --checkpoint "$run" --tasks "$task_list" --episodes "${EPISODES:-50}" --max-keyframes 25 \
    --shard-index "$i" --shard-count "$shards" --out "$run/success.s$i.results.json" > "$run/success.s$i.log" 2>&1 &
  pids+=($!)
done
for i in "${!pids[@]}"; do
  wait "${pids[$i]}" || { echo "bench success shard $i failed, see $run/success.s$i.log" >&2; exit 1; }
done
"$bin" merge "${parts[@]}" --out "$run/success.results.json" --json > "$run/success.json"
echo "done: $run (heldout.json, success.json)"
