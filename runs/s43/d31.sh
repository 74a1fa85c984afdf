#!/usr/bin/env bash
# Session 43, diagnostic D31: PB5's stack_blocks seeds that failed at 25 keyframes, re-run with
# the limit at 31 (runs/s43/d31/pb5_<seed>.json). Compare with runs/s43/d31.py.
cd /work/main
bin=${BIN:-/tmp/flowram-s42}; out=runs/s43/d31; mkdir -p $out
for seed in "$@"; do
  [ -s $out/pb5_$seed.json ] || $bin run --task stack_blocks --policy flowram --seed $seed --max-keyframes 31 --json > $out/pb5_$seed.json 2> $out/pb5_$seed.err
  echo "$seed done $(date +%T)"
done
