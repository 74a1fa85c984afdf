"""Diagnostic D31: PB5's stack_blocks at a 31-keyframe limit, from the 25-limit records
(docs/results/sw-s42/pb5) and the re-runs of their failures (runs/s43/d31/pb5_<seed>.json).
Checks that each re-run's first 25 keyframes are the 25-limit re-run's (runs/s43/fail/)."""
import json, math, os
rec = {}
for s in (1000, 1050):
    d = json.load(open(f'docs/results/sw-s42/pb5/stack_blocks.{s}.results.json'))
    for o in d['outcomes']:
        rec[o['seed']] = o
by = {2: [0, 0, 0], 3: [0, 0, 0], 4: [0, 0, 0]}  # successes at 25, at 31, episodes
same, checked, missing, used = 0, 0, [], []
for seed, o in sorted(rec.items()):
    c = o['variation'] % 3 + 2
    by[c][2] += 1
    if o['success']:
        by[c][0] += 1; by[c][1] += 1; continue
    p = f'runs/s43/d31/pb5_{seed}.json'
    try:
        r = json.load(open(p))
    except Exception:
        missing.append(seed); continue
    f = f'runs/s43/fail/pb5_{seed}.json'
    try:
        a = json.load(open(f))['actions']
    except Exception:
        a = None
    if a is not None:
        checked += 1
        same += all(max(abs(x - y) for x, y in zip(u, v)) < 1e-6 for u, v in zip(a, r['actions'][:25]))
    if r['success']:
        by[c][1] += 1; used.append((seed, r['keyframes']))
n25 = sum(v[0] for v in by.values()); n31 = sum(v[1] for v in by.values()); n = sum(v[2] for v in by.values())
print(f'D31 stack_blocks: {n25} at 25 -> {n31} at 31 of {n} (re-runs missing: {len(missing)})')
for c, (a, b, m) in by.items():
    print(f'  {c} blocks: {a}/{m} -> {b}/{m}')
print(f'  first 25 keyframes identical to the 25-limit re-run: {same} of {checked} checked')
print(f'  successes after keyframe 25 (seed, keyframes): {used}')
