#!/usr/bin/env bash
# Session 42: session 37's teacher-forced stack_blocks pick readout for a checkpoint (runs/stackread/later.py
# on held_stack_blocks + held_stack_blocks_1070), by this binary.  runs/s42/readout.sh CHECKPOINT NAME
set -u
cd /work/main
bin=${BIN:-/tmp/flowram-s42g}
mkdir -p runs/s42/readout
o=runs/s42/readout/$2.json
[ -s $o ] || $bin bench heldout --checkpoint $1 --data runs/data/held_stack_blocks,runs/data/held_stack_blocks_1070 \
  --train-data runs/data/stack_blocks-300-perturbed-0.03 --json > $o.tmp 2> runs/s42/readout/$2.err && mv $o.tmp $o
python3 runs/stackread/later.py $o
python3 -c "
import json; d=json.load(open('$o')); m=d['model']; print('$2 median', round(m['position_mm_median'],1), 'mean', round(m['position_mm_mean'],1), 'target', d.get('target_accuracy'))"
