#!/usr/bin/env bash
# Session 39, arm PS: train PS (seed 0), evaluate it, train PS-1 (seed 1), evaluate it, pair with SO-Y / SO-Y1.
set -u
cd /work/main
bin=/tmp/flowram-s38
for arm in ps ps-1; do
  if ! grep -q "trained to step 4000" runs/s39/$arm.log 2>/dev/null; then
    s=$(date +%s)
    $bin train --data runs/data/stack_blocks-300-perturbed-0.03 --out runs/s39/$arm --config runs/s39/$arm.toml > runs/s39/$arm.log 2>&1
    echo "$arm TRAIN DONE wall $(( $(date +%s) - s )) s $(date)"
  fi
  runs/s39/eval.sh $arm
  python3 runs/s39/pair.py
done
echo CHAIN DONE $(date)
