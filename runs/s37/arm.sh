#!/usr/bin/env bash
# Session 37 step 2 of an inference-only arm: PB5 with extra sampling options ARGS, seeds 1000-1049 and 1050-1099 per
# task, TASKS in order (stack_blocks first, for the futility stop), session 35's binary and controller profile (pairs
# with runs/s36/pb5-here). usage: runs/s37/arm.sh NAME "ARGS"
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
bin=/tmp/flowram-s36
ck=models/policy/pretrained/five-tasks
name=$1; args=$2; out=runs/s37/$name
mkdir -p $out
for task in ${TASKS:-stack_blocks open_drawer push_buttons slide_block close_jar}; do
  for seed in 1000 1050; do
    [ -s $out/$task.$seed.results.json ] && continue
    s=$(date +%s); pids=()
    for i in 0 1; do
      $bin bench success --checkpoint $ck --seed $seed --tasks $task --episodes 50 --max-keyframes 25 $args \
        --shard-index $i --shard-count 2 --out $out/$task.$seed.s$i.results.json > $out/$task.$seed.s$i.log 2>&1 &
      pids+=($!)
    done
    for p in "${pids[@]}"; do wait $p; done
    $bin merge $out/$task.$seed.s0.results.json $out/$task.$seed.s1.results.json --out $out/$task.$seed.results.json --json > $out/$task.$seed.json
    echo "$task $seed DONE wall $(( $(date +%s) - s )) s $(date)"
  done
  python3 runs/s37/pair.py $name
done
echo ARM DONE
