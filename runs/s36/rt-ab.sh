#!/usr/bin/env bash
# Session 36: the tick's QP update (P and A in one call, 4 scaling iterations) against session
# 35's code, one after another, alone on the machine: bench control (3 each, alternating), then
# bench realtime with the policy, 200,000 ticks each (new, old), default placement.
set -euo pipefail
cd /work/main
new=target/release/flowram
old=/tmp/flowram-s36
oldc=/tmp/controllers-old/controllers
out=runs/s36/rt
mkdir -p $out
$new bench policy --repeats 1 --json > $out/bench-policy-2.json 2> /dev/null
echo "policy done $(date)"
for i in 1 2 3; do
  $new bench control --json > $out/control-new-$i.json
  FLOWRAM_CONTROLLERS=$oldc $old bench control --json > $out/control-old-$i.json
done
echo "control done $(date)"
$new bench realtime --ticks ${TICKS:-200000} --with-policy --json > $out/rt-new.json 2> $out/rt-new.err
echo "rt new done $(date)"
FLOWRAM_CONTROLLERS=$oldc $old bench realtime --ticks ${TICKS:-200000} --with-policy --json > $out/rt-old.json 2> $out/rt-old.err
echo "rt old done $(date)"
