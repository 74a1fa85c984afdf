#!/usr/bin/env bash
# Session 37, arm MC step 1: teacher-forced held-out stack_blocks keyframes of PB5 with the mode consensus (8 and 16 samples)
set -u
cd /work/main
export FLOWRAM_CONTROLLERS=/tmp/controllers-old/controllers
bin=/tmp/flowram-s36
ck=models/policy/pretrained/five-tasks
for n in 8 16; do
  [ -s runs/s37/ho/mc$n.json ] && continue
  s=$(date +%s)
  $bin bench heldout --checkpoint $ck --data runs/data/held_stack_blocks,runs/data/held_stack_blocks_1070 \
    --train-data runs/data/held_stack_blocks --samples $n --consensus mode --json > runs/s37/ho/mc$n.json.tmp 2> runs/s37/ho/mc$n.err \
    && mv runs/s37/ho/mc$n.json.tmp runs/s37/ho/mc$n.json
  echo "mode of $n wall $(( $(date +%s) - s )) s $(date)"
  python3 runs/stackread/later.py runs/s37/ho/mc$n.json
done
echo MC DONE
