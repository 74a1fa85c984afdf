#!/usr/bin/env bash
# teacher-forced stack_blocks held-out keyframes of a checkpoint, by keyframe kind (index mod 6)
cd /work/main
c=$1; n=$(basename $c); task=${2:-stack_blocks}; tr=$(ls -d runs/data/${task}-*-perturbed-0.03 | head -1)
target/release/flowram bench heldout --checkpoint $c --data runs/data/held_$task --train-data $tr --json > runs/stackread/ho/$n-$task.json 2>runs/stackread/ho/err || tail -3 runs/stackread/ho/err
python3 -c "
import json,statistics as st,collections
d=json.load(open('runs/stackread/ho/$n-$task.json'))
by=collections.defaultdict(list)
for k in d['per_keyframe']: by[k['keyframe']%6].append(k['position_mm'])
print('$n $task', round(d['model']['position_mm_median'],1), round(d['model']['position_mm_mean'],1), {k: round(st.median(v),1) for k,v in sorted(by.items())}, 'target', d['target_accuracy'])
"
