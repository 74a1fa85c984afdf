#!/usr/bin/env bash
# Session 43, arm SG (docs/experiments.md): the shipped recipe + SW's task weights + GR's grounding
# loss, on the recipe's data collected on this machine in session 41, 14,000 steps, seed 0.
# Resumable: re-running resumes from runs/s43/sg/checkpoints (or from a committed copy restored there).
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s43}
d=runs/data
data=$d/open_drawer-100-perturbed-0.03,$d/push_buttons-300-perturbed-0.03,$d/slide_block-300-perturbed-0.03,$d/close_jar-300-perturbed-0.03,$d/stack_blocks-300-perturbed-0.03
s=$(date +%s)
if [ -d runs/s43/sg/checkpoints ]; then
  $bin train --data $data --out runs/s43/sg --resume || exit 1
else
  $bin train --data $data --out runs/s43/sg --config runs/s43/sg.toml || exit 1
fi
echo "[$(date +%H:%M:%S)] SG TRAIN DONE wall $(( $(date +%s) - s )) s"
