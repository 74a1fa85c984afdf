#!/usr/bin/env bash
# Session 32: A = the policy's threads share the control thread's core (--share-control-core, as before);
# C = they are kept off it (the new default). Alternated, 10^5 ticks each, paper-sized policy inferring.
cd /work/main
cp target/release/flowram /tmp/flowram-s32rt
for r in 1 2; do
  /tmp/flowram-s32rt bench realtime --ticks 100000 --with-policy --share-control-core --json > runs/rt/A$r.json 2> runs/rt/A$r.err
  /tmp/flowram-s32rt bench realtime --ticks 100000 --with-policy --json > runs/rt/C$r.json 2> runs/rt/C$r.err
done
echo DONE
