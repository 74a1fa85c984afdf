#!/usr/bin/env bash
# The Table C analogue: closed-loop success and inference latency against Euler steps.
#   scripts/table-c.sh OUT_DIR CHECKPOINT [CHECKPOINT...]
# Each CHECKPOINT (a run folder runs/NAME or a checkpoint folder; e.g. a run trained with DRS,
# such as the shipped recipe's, and one trained with `radius_schedule.kind = "global"` at the
# same compute) is evaluated by `bench success` on TASKS (comma-separated, default the five)
# at each of STEPS (default "2 4 8 16") Euler steps, EPISODES (default 20) held-out seeds per
# task from 1000, in SHARDS (default: one per core) processes side by side, merged into OUT_DIR/<name>-<steps>.json (name:
# the run's, as `bench grid` names arms). INFERENCE_ABLATION=1 also samples each checkpoint with
# global geometric tokens (`--no-drs`, no retraining): OUT_DIR/<name>-<steps>-global.json (not
# for a checkpoint trained with `kind = "global"`: both cells would be global, and `bench grid`
# refuses two records of the same cell).
# `bench grid` then prints the table and draws OUT_DIR/table_c.png (PLOT overrides the path).
# The latency column is the closed loop's (all consensus samples) with SHARDS evaluations
# sharing the cores; SHARDS=1 measures it unloaded, at twice the wall clock on 2 cores.
# A killed run continues where it stopped: each shard resumes its results file in
# OUT_DIR/shards, and one that holds another checkpoint's results is refused, not reused.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ $# -lt 2 ]; then
  echo "usage: scripts/table-c.sh OUT_DIR CHECKPOINT [CHECKPOINT...]" >&2
  exit 2
fi
out=$1
shift
scripts/setup.sh
cargo build --release --locked
bin=target/release/flowram
tasks="${TASKS:-open_drawer,push_buttons,slide_block,close_jar,stack_blocks}"
episodes="${EPISODES:-20}"
shards="${SHARDS:-$(nproc)}"
mkdir -p "$out/shards"
# Shards still running when this script stops (a failed shard, Ctrl-C) are stopped with it.
trap 'kill $(jobs -p) 2>/dev/null || true' EXIT
trap 'exit 130' INT TERM
name_of() { # the run's name for runs/NAME/checkpoints/step-N, else the folder's
  local path=${1%/}
  if [ "$(basename "$(dirname "$path")")" = checkpoints ]; then
    basename "$(dirname "$(dirname "$path")")"
  else
    basename "$path"
  fi
}
cells=()
cell() { # CHECKPOINT STEPS FILE [--no-drs]
  local checkpoint=$1 steps=$2 file=$3 pids=() parts=() i part
  shift 3
  cells+=("$file")
  for ((i = 0; i < shards; i++)); do
    part="$out/shards/$(basename "$file" .json).s$i-of-$shards.json"
    parts+=("$part")
    "$bin" bench success --checkpoint "$checkpoint" --tasks "$tasks" --episodes "$episodes" --steps "$steps" \
      --out "$part" --shard-index "$i" --shard-count "$shards" --json "$@" > "$part.log" 2>&1 &
    pids+=($!)
  done
  for i in "${!pids[@]}"; do
    wait "${pids[$i]}" || { echo "shard $i of $file failed, see ${parts[$i]}.log" >&2; exit 1; }
  done
  "$bin" merge "${parts[@]}" --out "$file" > /dev/null
  echo "$file ($(date -u +%H:%M:%S))"
}
names=()
for checkpoint in "$@"; do
  name=$(name_of "$checkpoint")
  for n in "${names[@]}"; do
    if [ "$n" = "$name" ]; then
      echo "two checkpoints are both named $name (their run's or folder's name): copy one to a folder of another name" >&2
      exit 2
    fi
  done
  names+=("$name")
done
for checkpoint in "$@"; do
  name=$(name_of "$checkpoint")
  for steps in ${STEPS:-2 4 8 16}; do
    cell "$checkpoint" "$steps" "$out/$name-$steps.json"
    if [ "${INFERENCE_ABLATION:-0}" = 1 ]; then
      cell "$checkpoint" "$steps" "$out/$name-$steps-global.json" --no-drs
    fi
  done
done
"$bin" bench grid "${cells[@]}" --plot "${PLOT:-$out/table_c.png}"
