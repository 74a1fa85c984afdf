#!/usr/bin/env bash
# Arm PW step 1 (pre-registered): GUR's weights, held-out keyframes teacher forced, posterior width w
set -euo pipefail
cd /work/main
bin=/tmp/flowram-s31
data=runs/data/open_drawer-100-perturbed-0.03,runs/data/push_buttons-300-perturbed-0.03,runs/data/slide_block-300-perturbed-0.03,runs/data/close_jar-300-perturbed-0.03,runs/data/stack_blocks-300-perturbed-0.03
held=runs/data/held_open_drawer,runs/data/held_push_buttons,runs/data/held_slide_block,runs/data/held_close_jar,runs/data/held_stack_blocks
for w in 0 0.01 0.02 0.04; do
  $bin bench heldout --checkpoint ${CK:-runs/gu/gur} --pointer-posterior-width $w --data $held --train-data $data --json > runs/pw/heldout-${NAME:-gur}-w$w.json
  echo "w=$w $(date)"
done
