#!/usr/bin/env bash
# Session 38: SO-R's training once its data is merged; SO-Y's evaluation once its training ends; then SO-R's evaluation.
set -u
cd /work/main
( while pgrep -f "collect --task stack_blocks" > /dev/null; do sleep 10; done
  grep -q "holds 300 episodes" runs/s38/collect-shuffled.log || { echo "SO-R DATA INCOMPLETE"; exit 1; }
  /tmp/flowram-s38 train --data runs/data/stack_blocks-300-perturbed-0.03-shuffled --out runs/s38/so-r --config runs/s38/stack-only.toml > runs/s38/so-r.log 2>&1
  echo "SO-R TRAIN DONE $(date)" ) &
trainer=$!
while pgrep -f "s38base train" > /dev/null; do sleep 10; done
echo "SO-Y TRAIN DONE $(date)"
runs/s38/eval.sh so-y
wait $trainer
runs/s38/eval.sh so-r
python3 runs/s38/pair.py
echo CHAIN DONE $(date)
