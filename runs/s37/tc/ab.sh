#!/usr/bin/env bash
# Session 37: OSQP's termination check every 10 (shipped) against every 5 iterations, bench control, alternated
cd /work/main
for i in 1 2 3; do
  /tmp/flowram-s37 bench control --json > runs/s37/tc/control-10-$i.json
  FLOWRAM_CONTROLLERS=/tmp/ctl5/controllers /tmp/flowram-s37 bench control --json > runs/s37/tc/control-5-$i.json
done
echo AB DONE
