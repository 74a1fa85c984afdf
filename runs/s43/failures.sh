#!/usr/bin/env bash
# Session 43: re-runs PB5's failed stack_blocks seeds (machine C records, docs/results/sw-s42/pb5)
# closed loop with `flowram run --json` (the final block positions and every executed keyframe),
# and the expert on the same seed (the platform's centre and the stacking order), for reading the
# failures one by one (runs/s43/failures.py).
cd /work/main
bin=${BIN:-/tmp/flowram-s42}
out=runs/s43/fail; mkdir -p $out
ck=${CK:-models/policy/pretrained/five-tasks}; arm=${ARM:-pb5}
for seed in "$@"; do
  [ -s $out/expert_$seed.json ] || $bin run --task stack_blocks --seed $seed --json > $out/expert_$seed.json 2>/dev/null
  [ -s $out/${arm}_$seed.json ] || $bin run --task stack_blocks --policy flowram --checkpoint $ck --seed $seed --json > $out/${arm}_$seed.json 2> $out/${arm}_$seed.err
  echo "$seed done $(date +%T)"
done
