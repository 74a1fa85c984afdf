#!/usr/bin/env bash
# Builds runs/note/note41.md from its parts with SW's status (the step its committed checkpoint reached).
set -eu
cd /work/main/runs/note
last=$(cat ../s41/sw/checkpoints/latest); step=$((10#${last#step-}))
if [ "$step" = 14000 ]; then
  head="Its training finished (14,000 steps); its weights are committed (\`runs/s41/sw-checkpoint\`), so the evaluation needs no retraining."
  res="**Training finished: 14,000 steps**; the EMA weights, config and trainer state are committed in \`runs/s41/sw-checkpoint\` (with \`metrics.csv\`). **Not evaluated:** each task takes about 15 min per arm here, and the session ended first. \`runs/s41/eval.sh\` runs it (paired halves, stack_blocks first)."
else
  head="Its training reached step $step of 14,000 when the session had to stop. The checkpoint is committed whole (\`runs/s41/sw-resume\`, with the optimizer), so the next session resumes it exactly on the same data."
  res="**Training reached step $step of 14,000** before the session's end. The checkpoint is committed whole (model, optimizer, EMA) in \`runs/s41/sw-resume\`. \`train --resume\` continues it exactly if the data is the same: collected again by this revision on this machine kind. On another kind the data differs at float rounding, and the resumed run would be a mixed draw, to be said as such. **Not evaluated.**"
fi
sed "s|SW_HEAD_PLACEHOLDER|$head|" note41-head.md > note41.md
echo >> note41.md; cat standing41.md >> note41.md
echo >> note41.md; sed "s|SW_RESULT_PLACEHOLDER|$res|" session41.md >> note41.md
echo >> note41.md; cat issue13-41.md >> note41.md
echo >> note41.md; cat checks41.md >> note41.md
echo >> note41.md; cat next41.md >> note41.md
grep -c PLACEHOLDER note41.md || true
wc -c note41.md
