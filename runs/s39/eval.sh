#!/usr/bin/env bash
# Session 39, arm PS: stack_blocks closed loop on seeds 1000-1099 (two shards), then the teacher-forced
# later-pick readout on session 37's 40 held-out episodes. usage: runs/s38/eval.sh NAME (runs/s38/NAME is the run)
set -u
cd /work/main
bin=/tmp/flowram-s38
run=runs/s39/$1
if [ ! -s $run/success.results.json ]; then
  s=$(date +%s); pids=()
  for i in 0 1; do
    $bin bench success --checkpoint $run --tasks stack_blocks --seed 1000 --episodes 100 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/success.s$i.results.json > $run/success.s$i.log 2>&1 &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  $bin merge $run/success.s0.results.json $run/success.s1.results.json --out $run/success.results.json --json > $run/success.json
  echo "$1 success DONE wall $(( $(date +%s) - s )) s $(date)"
fi
if [ ! -s $run/heldout.json ]; then
  $bin bench heldout --checkpoint $run --data runs/data/held_stack_blocks,runs/data/held_stack_blocks_1070 \
    --train-data runs/data/held_stack_blocks --json > $run/heldout.json.tmp 2> $run/heldout.err && mv $run/heldout.json.tmp $run/heldout.json
fi
python3 runs/stackread/later.py $run/heldout.json
echo EVAL DONE $1
