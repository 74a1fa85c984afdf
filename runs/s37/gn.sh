#!/usr/bin/env bash
# Session 37, arm GN step 1: teacher-forced held-out stack_blocks keyframes of PB5 with --pointer-guidance 2
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
s=$(date +%s)
/tmp/flowram-s36 bench heldout --checkpoint models/policy/pretrained/five-tasks --data runs/data/held_stack_blocks,runs/data/held_stack_blocks_1070 \
  --train-data runs/data/held_stack_blocks --pointer-guidance 2 --json > runs/s37/ho/gn2.json.tmp 2> runs/s37/ho/gn2.err && mv runs/s37/ho/gn2.json.tmp runs/s37/ho/gn2.json
echo "gn2 wall $(( $(date +%s) - s )) s $(date)"
python3 runs/stackread/later.py runs/s37/ho/gn2.json
echo GN DONE
