#!/usr/bin/env bash
# Session 43: waits for SG's training (pid $1), then evaluates SG on stack_blocks, seeds 1000+50 and
# 1050+50 (two shards each, merged), into runs/s41/eval/sg/ beside PB5's machine-C halves (same
# seeds; PB5's were run by /tmp/flowram-s42, whose inference code this binary shares). Resumable.
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s43}
stamp() { echo "[$(date +%H:%M:%S)] $*"; }
[ -z "${1:-}" ] || while kill -0 "$1" 2>/dev/null; do sleep 10; done
[ "$(cat runs/s43/sg/checkpoints/latest 2>/dev/null)" = step-000014000 ] || { stamp "SG has not reached step 14000"; exit 1; }
for seed in 1000 1050; do
  o=runs/s41/eval/sg/stack_blocks.$seed; mkdir -p runs/s41/eval/sg
  [ -f $o.results.json ] && continue
  pids=()
  for i in 0 1; do
    $bin bench success --checkpoint runs/s43/sg --tasks stack_blocks --episodes 50 --seed $seed --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $o.s$i.results.json > $o.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p || { stamp "shard failed"; exit 1; }; done
  $bin merge $o.s0.results.json $o.s1.results.json --out $o.results.json --json > $o.json
  stamp "SG stack_blocks $seed done"; python3 runs/s43/pair_sg.py
done
stamp "SG EVAL DONE"
