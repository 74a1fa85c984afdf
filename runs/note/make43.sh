#!/usr/bin/env bash
# Builds runs/note/note43.md from its parts with SG's status (training step, alone rate, evaluation so far).
# SG_DONE_TEXT (optional, environment): the text that replaces the status when SG's result is read.
set -eu
cd /work/main/runs/note
last=$(cat ../s43/sg/checkpoints/latest); step=$((10#${last#step-}))
rate=$(python3 -c "
import csv
r=[l for l in csv.reader(open('../s43/sg/metrics.csv')) if l and l[0][0].isdigit()]
a,b=r[-100] if len(r)>100 else r[0],r[-1]
print(f'{(float(b[-1])-float(a[-1]))/(int(b[0])-int(a[0])):.2f}')")
pair=$(cd /work/main && python3 runs/s43/pair_sg.py 2>/dev/null || true)
[ -f sgdone43.txt ] && SG_DONE_TEXT=$(cat sgdone43.txt)
if [ -n "${SG_DONE_TEXT:-}" ]; then
  head="$SG_DONE_TEXT"; status=$(echo "$SG_DONE_TEXT" | sed "s/^\*\*trained/**Trained/")
elif [ "$step" -lt 14000 ]; then
  head="**training was at step $step of 14,000 when this note was filed ($rate s a step alone), so SG is not evaluated.** Its resumable checkpoint (model, optimizer, EMA, trainer state) is committed in \`runs/s43/sg-resume\`."
  status="**Training was at step $step of 14,000 when this note was filed. Not evaluated.** The checkpoint is committed whole in \`runs/s43/sg-resume\`. Copy it to \`runs/s43/sg/checkpoints/\` (with a \`latest\` file naming it) and \`runs/s43/sg.sh\` resumes it exactly, on the same data: the recipe's, collected on machine C. \`runs/s43/sg_eval.sh\` then evaluates stack_blocks."
else
  head="**trained (14,000 steps, $rate s a step alone; weights in \`runs/s43/sg-checkpoint\`); its stack_blocks evaluation was under way when this note was filed: ${pair:-no episode merged yet}.** Not decided."
  status="**Trained: 14,000 steps, $rate s a step alone; weights in \`runs/s43/sg-checkpoint\`. The stack_blocks evaluation was under way when this note was filed: ${pair:-no half merged yet}.** No decision yet. \`runs/s43/sg_eval.sh\` resumes it (bench success skips the episodes its results files hold)."
fi
sed "s|HEAD_SG|$head|" note43-head.md > note43.md
echo >> note43.md; cat standing43.md >> note43.md
echo >> note43.md; sed "s|SG_STATUS|$status|" session43.md >> note43.md
echo >> note43.md; cat issue13-43.md >> note43.md
echo >> note43.md; sed "s|TESTS_PLACEHOLDER|$(cat tests43.txt)|; s|SG_RATE|$rate|; s|BEFORE_STOP|$(cat before43.txt 2>/dev/null || echo 'not yet read')|" checks43.md >> note43.md
echo >> note43.md; cat next43.md >> note43.md
grep -n "PLACEHOLDER\|HEAD_SG\|SG_STATUS\|SG_RATE\|BEFORE_STOP" note43.md || true
wc -c note43.md
