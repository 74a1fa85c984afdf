#!/usr/bin/env bash
# Session 32: push_buttons-only proxy for the sequence order. usage: train.sh NAME CONFIG [BIN]
set -euo pipefail
cd /work/main
name=$1; cfg=$2; bin=${3:-/tmp/flowram-s32}
run=runs/order/$name
s=$(date +%s)
$bin train --data runs/data/push_buttons-300-perturbed-0.03 --out $run --config $cfg --steps 2800 > runs/order/$name.train.log 2>&1
echo "$name TRAIN WALL $(( $(date +%s) - s )) $(date)"
$bin bench heldout --checkpoint $run --pointer-posterior --data runs/data/held_push_sequences,runs/data/held_push_sequences_1070,runs/data/held_push_sequences_1120 --train-data runs/data/push_buttons-300-perturbed-0.03 --json > runs/order/seq90-$name.json 2>runs/order/seq90-$name.err
echo "$name PROXY DONE $(date)"
python3 runs/pushread/seq.py runs/order/seq90-$name.json
