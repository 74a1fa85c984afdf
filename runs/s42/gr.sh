#!/usr/bin/env bash
# Session 42, arm GR (docs/experiments.md): train the shipped recipe + flow.grounding_weight = 1.0 on
# the recipe's data collected here (session 41), 14,000 steps, seed 0; then the stack_blocks pick
# readout (GR, PB5, SW) and GR's stack_blocks closed loop, seeds 1000+50 and 1050+50, into
# runs/s41/eval/gr/ beside SW's and PB5's halves (same seeds, binary with the same inference code).
# Resumable: training resumes, bench success skips done episodes.
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s42g}
d=runs/data
stamp() { echo "[$(date +%H:%M:%S)] $*"; }
data=$d/open_drawer-100-perturbed-0.03,$d/push_buttons-300-perturbed-0.03,$d/slide_block-300-perturbed-0.03,$d/close_jar-300-perturbed-0.03,$d/stack_blocks-300-perturbed-0.03
s=$(date +%s)
if [ -d runs/s42/gr/checkpoints ]; then
  $bin train --data $data --out runs/s42/gr --resume || exit 1
else
  $bin train --data $data --out runs/s42/gr --config runs/s42/gr.toml || exit 1
fi
stamp "GR TRAIN DONE wall $(( $(date +%s) - s )) s"
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
half gr runs/s42/gr stack_blocks 1000
half gr runs/s42/gr stack_blocks 1050
runs/s42/readout.sh runs/s42/gr gr
stamp "GR DONE"
