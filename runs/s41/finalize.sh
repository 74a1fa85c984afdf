#!/usr/bin/env bash
# Session 41's end: SW's weights into git. Finished: the EMA weights, config and trainer state of
# step 14,000 in runs/s41/sw-checkpoint. Not finished: the latest checkpoint whole (model,
# optimizer, EMA) in runs/s41/sw-resume, for `train --resume` (copy it to runs/s41/sw/checkpoints).
set -eu
cd /work/main
last=$(cat runs/s41/sw/checkpoints/latest)
c=runs/s41/sw/checkpoints/$last
mkdir -p runs/s41/sw-checkpoint
cp runs/s41/sw/metrics.csv runs/s41/sw-checkpoint/
if [ "$last" = step-000014000 ]; then
  cp $c/config.json $c/ema.safetensors $c/trainer.json runs/s41/sw-checkpoint/
  git add -f runs/s41/sw-checkpoint
else
  rm -rf runs/s41/sw-resume && mkdir -p runs/s41/sw-resume/checkpoints
  cp -r $c runs/s41/sw-resume/checkpoints/ && cp runs/s41/sw/checkpoints/latest runs/s41/sw-resume/checkpoints/
  git add -f runs/s41/sw-resume runs/s41/sw-checkpoint/metrics.csv
fi
echo "$last"
