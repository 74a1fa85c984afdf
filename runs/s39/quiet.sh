#!/usr/bin/env bash
# Session 39: the issue-13 figures on a quiet machine. Waits for PS's training to end, pauses the
# chain's evaluation (SIGSTOP), runs the benches alone, then resumes it (SIGCONT).
# old = /tmp/flowram-s38 (session 38's code), new = /tmp/flowram-s39 (OSQP skipped where no row is active)
set -u
cd /work/main
out=docs/results/realtime-s39; mkdir -p $out
until grep -q "ps TRAIN DONE" runs/s39/chain.log; do sleep 5; done
sleep 3
pids=$(pgrep -f "flowram-s38 bench success")
[ -n "$pids" ] && kill -STOP $pids
echo "paused: $pids $(date)"
for r in 1 2 3; do
  for b in s38 s39; do
    /tmp/flowram-$b bench control --json > $out/control-$b-$r.json 2> /dev/null
  done
done
/tmp/flowram-s39 bench realtime --ticks 1000000 --with-policy --json > $out/default-1e6.json 2> $out/default-1e6.err
/tmp/flowram-s39 bench policy --repeats 1 --json > $out/bench-policy.json 2> $out/bench-policy.err
[ -n "$pids" ] && kill -CONT $pids
echo "resumed $(date)"
