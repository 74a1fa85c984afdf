#!/usr/bin/env bash
# Session 41: waits for SW's training (pid $1) to exit, then evaluates SW and the shipped PB5 on the
# same seeds, in paired halves so that whatever is done when the session ends pairs: per task,
# SW 1000+50, PB5 1000+50, SW 1050+50, PB5 1050+50 (two shards each, merged), stack_blocks first.
# Resumable (bench success skips the episodes its results file holds). SW's weights: runs/s41/sw-checkpoint
# (committed: EMA weights, config, trainer state, metrics). Records pair only within one machine kind
# and binary: on another kind, move the halves done elsewhere aside (or name another out dir) first.
#   runs/s41/eval.sh            (no training to wait for)
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s41}   # a release build of this revision (cp target/release/flowram)
stamp() { echo "[$(date +%H:%M:%S)] $*"; }
[ -z "${1:-}" ] || while kill -0 "$1" 2>/dev/null; do sleep 10; done
sw=${SW:-runs/s41/sw-checkpoint}
[ -f $sw/ema.safetensors ] || { echo "no SW checkpoint at $sw"; exit 1; }
half() { # ARM CHECKPOINT TASK SEED
  local arm=$1 ck=$2 task=$3 seed=$4 pids=() i
  local o=runs/s41/eval/$arm/$task.$seed
  mkdir -p runs/s41/eval/$arm
  [ -f $o.results.json ] && { stamp "$arm $task $seed already merged"; return; }
  for ((i = 0; i < 2; i++)); do
    $bin bench success --checkpoint $ck --tasks $task --episodes 50 --seed $seed --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $o.s$i.results.json > $o.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p || { stamp "$arm $task $seed shard failed"; return 1; }; done
  $bin merge $o.s0.results.json $o.s1.results.json --out $o.results.json --json > $o.json
  stamp "eval $arm $task $seed done: $(python3 -c "import json;d=json.load(open('$o.results.json'));print(sum(o['success'] for o in d['outcomes']),'/',len(d['outcomes']))" 2>/dev/null)"
}
for task in ${TASKS:-stack_blocks close_jar slide_block push_buttons open_drawer}; do
  for seed in 1000 1050; do
    half sw $sw $task $seed
    half pb5 models/policy/pretrained/five-tasks $task $seed
  done
done
stamp "EVAL DONE"
