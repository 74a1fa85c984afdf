#!/usr/bin/env bash
# Session 37, arm ES step 1: teacher-forced held-out stack_blocks keyframes of PB5 at STEPS Euler steps
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
bin=/tmp/flowram-s36
ck=models/policy/pretrained/five-tasks
mkdir -p runs/s37/ho
for st in ${STEPS:-8 16 32}; do
  [ -s runs/s37/ho/es$st.json ] && continue
  s=$(date +%s)
  $bin bench heldout --checkpoint $ck --data runs/data/held_stack_blocks,runs/data/held_stack_blocks_1070 \
    --train-data runs/data/held_stack_blocks --steps $st --json > runs/s37/ho/es$st.json.tmp 2> runs/s37/ho/es$st.err \
    && mv runs/s37/ho/es$st.json.tmp runs/s37/ho/es$st.json
  echo "steps $st wall $(( $(date +%s) - s )) s $(date)"
  python3 runs/stackread/later.py runs/s37/ho/es$st.json
done
echo PROXY DONE
