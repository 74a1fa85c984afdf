#!/usr/bin/env bash
# Session 40, arm SW: five-task recipe + task_weights {stack_blocks 2, open_drawer 0.5}, 14,000 steps, seed 0,
# session 36's binary (the one PB5's record on this machine kind was evaluated with). Resumes if checkpoints exist.
set -u
cd /work/main
bin=/tmp/flowram-s36
d=runs/data
data=$d/open_drawer-100-perturbed-0.03,$d/push_buttons-300-perturbed-0.03,$d/slide_block-300-perturbed-0.03,$d/close_jar-300-perturbed-0.03,$d/stack_blocks-300-perturbed-0.03
s=$(date +%s)
if [ -d runs/s40/sw/checkpoints ]; then
  $bin train --data $data --out runs/s40/sw --resume
else
  $bin train --data $data --out runs/s40/sw --config runs/s40/sw.toml
fi
echo "SW TRAIN DONE wall $(( $(date +%s) - s )) s $(date)"
