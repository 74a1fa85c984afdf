#!/usr/bin/env bash
# Session 42: commits GR's final weights once its training has finished (drops the resumable copy).
set -eu
cd /work/main
l=$(cat runs/s42/gr/checkpoints/latest)
[ "$l" = step-000014000 ] || { echo "GR at $l, not finished"; exit 1; }
mkdir -p runs/s42/gr-checkpoint
cp runs/s42/gr/checkpoints/$l/{config.json,ema.safetensors,trainer.json} runs/s42/gr/metrics.csv runs/s42/gr-checkpoint/
git rm -rq runs/s42/gr-resume
git add -f runs/s42/gr-checkpoint runs/s42/gr.log
git commit -qm "GR trained (14,000 steps on machine C): its final weights committed in runs/s42/gr-checkpoint; the resumable copy dropped"
echo committed
