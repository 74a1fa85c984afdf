#!/usr/bin/env bash
# Session 31: teacher-forced proxy for push_buttons' sequences (held_push_sequences*: seeds 1070-1099 and 1120-1149 too,
# 1020-1049, variations 20-49), each checkpoint with the posterior, as its closed-loop records.
set -u
cd /work/main
bin=/tmp/flowram-s31
for arm in gur:runs/gu/gur gur1:runs/s1/gur1 se:runs/se/se se1:runs/s1/se1 pc:runs/pc/pc; do
  IFS=: read name ck <<< "$arm"
  [ -s runs/pushread/seq90-$name.json ] && continue
  $bin bench heldout --checkpoint $ck --pointer-posterior --data runs/data/held_push_sequences,runs/data/held_push_sequences_1070,runs/data/held_push_sequences_1120 --train-data runs/data/push_buttons-300-perturbed-0.03 --json > runs/pushread/seq90-$name.json 2>runs/pushread/seq90-$name.err
  echo "$name $(date)"
done
