#!/usr/bin/env bash
# Session 32: PO-LA after PO-B's training; then push_buttons closed loop (50 episodes, 2 shards) for both.
set -u
cd /work/main
until grep -q "base TRAIN WALL" runs/order/base.log; do sleep 10; done
runs/order/train.sh la runs/order/la.toml /tmp/flowram-s32la > runs/order/la.log 2>&1
for name in base la; do
  run=runs/order/$name
  for i in 0 1; do
    /tmp/flowram-s32la bench success --checkpoint $run --tasks push_buttons --episodes 50 --max-keyframes 25 \
      --shard-index $i --shard-count 2 --out $run/push.s$i.results.json > $run/push.s$i.log 2>&1 &
  done
  wait
  /tmp/flowram-s32la merge $run/push.s0.results.json $run/push.s1.results.json --out $run/push.results.json --json > $run/push.json
  echo "$name PUSH DONE $(date)"
done
/tmp/flowram-s32la bench compare runs/order/la/push.results.json runs/order/base/push.results.json --json > runs/order/la-vs-base.json
echo "ALL DONE $(date)"
