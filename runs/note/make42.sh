#!/usr/bin/env bash
# Builds runs/note/note42.md from its parts with GR's status (the step its committed checkpoint reached).
set -eu
cd /work/main/runs/note
last=$(cat ../s42/gr/checkpoints/latest); step=$((10#${last#step-}))
head="**GR's training was at step $step of 14,000 when this note was filed (0.41 s a step alone), so GR has not been evaluated.** A checkpoint with its optimizer is committed (\`runs/s42/gr-resume\`), so the next session can resume it."
res="**Training was at step $step of 14,000 when this note was filed. Not evaluated.** The checkpoint is committed whole (model, optimizer, EMA) in \`runs/s42/gr-resume\`. \`runs/s42/gr.sh\` resumes it exactly on the same data (the recipe's, collected on machine C), then evaluates stack_blocks and the readout."
cp note42-head.md note42.md
echo >> note42.md; cat standing42.md >> note42.md
echo >> note42.md; cat session42.md >> note42.md
echo >> note42.md; cat issue13-42.md >> note42.md
echo >> note42.md; sed "s|TESTS_PLACEHOLDER|$(cat tests42.txt)|" checks42.md >> note42.md
echo >> note42.md; cat next42.md >> note42.md
grep -c PLACEHOLDER note42.md || true
wc -c note42.md
