#!/usr/bin/env bash
# Session 43: puts SG into git. Finished: its final weights in runs/s43/sg-checkpoint (the resumable
# copy dropped). Not finished: its latest checkpoint whole (model, optimizer, EMA, trainer state) in
# runs/s43/sg-resume, for an exact resume.
set -eu
cd /work/main
l=$(cat runs/s43/sg/checkpoints/latest)
if [ "$l" = step-000014000 ]; then
  mkdir -p runs/s43/sg-checkpoint
  cp runs/s43/sg/checkpoints/$l/{config.json,ema.safetensors,trainer.json} runs/s43/sg/metrics.csv runs/s43/sg-checkpoint/
  [ -d runs/s43/sg-resume ] && git rm -rq runs/s43/sg-resume
  git add -f runs/s43/sg-checkpoint runs/s43/sg.log
  git commit -qm "SG trained (14,000 steps on machine C): its final weights committed in runs/s43/sg-checkpoint"
else
  rm -rf runs/s43/sg-resume; mkdir -p runs/s43/sg-resume
  cp -r runs/s43/sg/checkpoints/$l runs/s43/sg-resume/ && echo "$l" > runs/s43/sg-resume/latest
  cp runs/s43/sg/metrics.csv runs/s43/sg-resume/
  git add -f runs/s43/sg-resume runs/s43/sg.log
  git commit -qm "SG's resumable checkpoint at $l (model, optimizer, EMA, trainer state), in case the session ends before it finishes"
fi
echo "committed $l"
