#!/usr/bin/env bash
# The Table C analogue: closed-loop success and inference latency against Euler steps.
#   scripts/table-c.sh OUT_DIR CHECKPOINT [CHECKPOINT...]
# Each CHECKPOINT (a run folder runs/NAME or a checkpoint folder; e.g. the shipped
# models/policy/pretrained/five-tasks, trained with DRS, and a run trained with
# `radius_schedule.kind = "global"` at the same compute) is evaluated by `bench success` on the
# five tasks at each of STEPS (default "2 4 8 16") Euler steps, EPISODES (default 20) held-out
# seeds per task from 1000, in SHARDS (default: one per core) processes side by side, merged into
# OUT_DIR/<checkpoint name>-<steps>.json. INFERENCE_ABLATION=1 also samples each checkpoint with
# global geometric tokens (`--no-drs`, no retraining): OUT_DIR/<name>-<steps>-global.json.
# `bench grid` then prints the table and draws OUT_DIR/table_c.png (PLOT overrides the path).
# Cells already in OUT_DIR are kept, so a killed run continues where it stopped.
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
tasks=open_drawer,push_buttons,slide_block,close_jar,stack_blocks
episodes="${EPISODES:-20}"
shards="${SHARDS:-$(nproc)}"
mkdir -p "$out"
cells=()
cell() { # CHECKPOINT STEPS FILE [--no-drs]
  local checkpoint=$1 steps=$2 file=$3 pids=() parts=() i
  shift 3
  cells+=("$file")
  [ -f "$file" ] && return
  for ((i = 0; i < shards; i++)); do
    parts+=("$file.s$i")
    "$bin" bench success --checkpoint "$checkpoint" --tasks "$tasks" --episodes "$episodes" --steps "$steps" \
      --out "$file.s$i" --shard-index "$i" --shard-count "$shards" --json "$@" > "$file.s$i.log" 2>&1 &
    pids+=($!)
  done
  for i in "${!pids[@]}"; do
    wait "${pids[$i]}" || { echo "shard $i of $file failed, see $file.s$i.log" >&2; exit 1; }
  done
  "$bin" merge "${parts[@]}" --out "$file" > /dev/null
  for i in "${!parts[@]}"; do rm -f "${parts[$i]}" "${parts[$i]}.log"; done
  echo "$file done ($(date -u +%H:%M:%S))"
}
for checkpoint in "$@"; do
  name=$(basename "$checkpoint")
  for steps in ${STEPS:-2 4 8 16}; do
    cell "$checkpoint" "$steps" "$out/$name-$steps.json"
    if [ "${INFERENCE_ABLATION:-0}" = 1 ]; then
      cell "$checkpoint" "$steps" "$out/$name-$steps-global.json" --no-drs
    fi
  done
done
"$bin" bench grid "${cells[@]}" --plot "${PLOT:-$out/table_c.png}"
