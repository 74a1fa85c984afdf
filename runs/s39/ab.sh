#!/usr/bin/env bash
# Session 39: bench realtime with the policy, 10^5 ticks, alternating session 38's binary (OSQP
# every tick) and session 39's (OSQP skipped where no row is active), twice each, alone.
set -u
cd /work/main
out=docs/results/realtime-s39
for r in 1 2; do
  for b in s38 s39; do
    /tmp/flowram-$b bench realtime --ticks 100000 --with-policy --json > $out/ab-$b-$r.json 2> /dev/null
  done
done
echo AB DONE $(date)
