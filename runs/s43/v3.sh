#!/usr/bin/env bash
# Session 43 prototype: stack_blocks' expert with 5 keyframes per block (no lift after a release
# but the last; /tmp/flowram-v3 built from a temporary edit) over seeds; prints success, keyframes.
cd /work/main
for seed in $(seq ${1:-0} ${2:-59}); do
  ${BIN:-/tmp/flowram-v3} run --task stack_blocks --seed $seed --json > runs/s43/${OUT:-v3}/$seed.json 2>/dev/null
  python3 -c "import json;d=json.load(open('runs/s43/${OUT:-v3}/$seed.json'));print($seed,d['variation'],d['success'],d['keyframes'],d['problems'])"
done
