#!/usr/bin/env bash
# Session 35 chain: collection, LP5 / LP5-1 on the corrected push_buttons, PB5 training alone,
# then PB5-1 training beside PB5's evaluation, then PB5-1's evaluation.
set -euo pipefail
cd /work/main
while [ ! -f runs/data/held_push_buttons/index.json ]; do sleep 10; done
TASKS=push_buttons HELDOUT=0 runs/pb/confirm.sh models/policy/pretrained/five-tasks runs/pb/lp5-push
TASKS=push_buttons HELDOUT=0 runs/pb/confirm.sh runs/lp/lp5-1 runs/pb/lp5-1-push
runs/pb/train.sh pb5
runs/pb/train.sh pb5-1 > runs/pb/train-pb5-1.log 2>&1 &
t=$!
runs/pb/confirm.sh runs/pb/pb5 runs/pb/pb5
wait $t
runs/pb/confirm.sh runs/pb/pb5-1 runs/pb/pb5-1
echo CHAIN DONE $(date)
