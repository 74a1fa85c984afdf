#!/usr/bin/env python3
"""Index-2 readout on three-button held-out episodes (held_push_sequences 15-29): where the goal
pointer g, the position pointer p and the keyframe land (nearest of T1/T2/T3 within 3 cm)."""
import json, subprocess, sys, math, collections
B = '/tmp/flowram-s32'
ck = sys.argv[1]; extra = sys.argv[2:]
def rec(ep, k):
    return json.loads(subprocess.run([B, 'predict', '--checkpoint', ck, '--episode', ep, '--keyframe', str(k), '--samples', '8', '--json'] + extra, capture_output=True, text=True, check=True).stdout)
h = lambda a, b: math.hypot(a[0]-b[0], a[1]-b[1])
def lab(x, T):
    d = [h(x, t) for t in T]; i = min(range(3), key=lambda j: d[j])
    return f'T{i+1}' if d[i] < 0.03 else 'X'
tot = {k: collections.Counter() for k in ('g', 'p', 'kf', 'exec')}
for e in range(15, 30):
    ep = f'/work/main/runs/data/held_push_sequences/episode_{e:05d}.safetensors'
    T = [rec(ep, k)['recorded']['position'] for k in (0,)] if False else None
    r = rec(ep, 2)
    T = [rec(ep, 0)['recorded']['position'], r['recorded']['position'], rec(ep, 4)['recorded']['position']]
    c = {k: collections.Counter() for k in ('g', 'p', 'kf')}
    for p in r['predictions']:
        c['g'][lab(p['pointer']['goal'], T)] += 1; c['p'][lab(p['pointer']['pointed'], T)] += 1; c['kf'][lab(p['keyframe']['position'], T)] += 1
    ex = lab(r['predictions'][r['executed']]['keyframe']['position'], T)
    for k in c: tot[k].update(c[k])
    tot['exec'][ex] += 1
    betas = [round(p['pointer']['beta'], 2) for p in r['predictions']]
    print(e, r['instruction'], '| g', dict(c['g']), 'p', dict(c['p']), 'kf', dict(c['kf']), 'exec', ex, 'beta', betas[:3], flush=True)
print('total', {k: dict(v) for k, v in tot.items()})
