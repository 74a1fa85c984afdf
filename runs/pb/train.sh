#!/usr/bin/env bash
# Session 35, arms PB5 / PB5-1 (pre-registered in docs/experiments.md): LP5 / LP5-1 retrained
# on push_buttons expert version 2; trained one after the other (14,000 steps each).
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s35
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
for arm in "$@"; do
  run=runs/pb/$arm
  s=$(date +%s)
  if [ -d $run/checkpoints ]; then $bin train --data $data --out $run --resume --steps 14000
  else $bin train --data $data --out $run --config runs/lp/${arm/pb/lp}.toml --steps 14000; fi
  echo "$arm TRAIN WALL $(( $(date +%s) - s )) $(date)"
done
