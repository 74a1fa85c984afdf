#!/usr/bin/env bash
# Session 34, arms CF5 / CF5-1 (pre-registered in docs/experiments.md): LP5's recipe with
# flow.instruction_dropout = 0.1; trained one after the other (14,000 steps each).
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s34
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
for arm in "$@"; do
  run=runs/cf/$arm
  s=$(date +%s)
  if [ -d $run/checkpoints ]; then $bin train --data $data --out $run --resume --steps 14000
  else $bin train --data $data --out $run --config runs/cf/$arm.toml --steps 14000; fi
  echo "$arm TRAIN WALL $(( $(date +%s) - s )) $(date)"
done
