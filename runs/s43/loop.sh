#!/bin/bash
cd /work/main
for i in $(seq 1 ${1:-6}); do
  s=$(date +%s)
  target/release/deps/pretrained-ed2c61f55a1c7997 > runs/s43/pre_$i.log 2>&1
  echo "run $i rc=$? $(( $(date +%s)-s ))s" >> runs/s43/loop.txt
done
