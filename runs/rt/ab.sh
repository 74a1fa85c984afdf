#!/usr/bin/env bash
# Session 32: does keeping the policy's threads off the control thread's core cut the tick's compute tail?
# A = as shipped; B = the process started on core 0 only (taskset), so the policy and its thread pool
# stay on core 0 while the control thread pins itself to core 1 (the last core), as it always does.
cd /work/main
for r in 1 2; do
  target/release/flowram bench realtime --ticks 100000 --with-policy --json > runs/rt/a$r.json 2> runs/rt/a$r.err
  taskset -c 0 target/release/flowram bench realtime --ticks 100000 --with-policy --json > runs/rt/b$r.json 2> runs/rt/b$r.err
done
echo DONE
