#!/usr/bin/env python3
"""Pointer readouts on held-out slide_block episodes: readout.py CHECKPOINT [KEYFRAME]
g's distance to the named zone and to the block; p's to the block; beta; error."""
import json, subprocess, sys, statistics as st, math
import os
B = os.environ.get('FLOWRAM', 'target/release/flowram')  # run from the repository root
ck = sys.argv[1]; kf = int(sys.argv[2]) if len(sys.argv) > 2 else 0
def rec(ep, k):
    r = json.loads(subprocess.run([B, 'predict', '--checkpoint', ck, '--episode', ep, '--keyframe', str(k), '--samples', '8', '--json'], capture_output=True, text=True, check=True).stdout)
    return r
rows = []
for e in range(10):
    ep = f'runs/data/held_slide_block/episode_{e:05d}.safetensors'
    k1 = rec(ep, 1)['recorded']['position']; k2 = rec(ep, 2)['recorded']['position']
    dx, dy = k2[0]-k1[0], k2[1]-k1[1]; n = math.hypot(dx, dy); dx, dy = dx/n, dy/n
    block = (k1[0]+0.055*dx, k1[1]+0.055*dy); zone = (k2[0]+0.03*dx, k2[1]+0.03*dy)
    r = rec(ep, kf)
    ex = r['predictions'][r['executed']]
    g = [p['pointer']['goal'] for p in r['predictions']]; pp = [p['pointer']['pointed'] for p in r['predictions']]
    h = lambda a, b: math.hypot(a[0]-b[0], a[1]-b[1]) * 1000
    dirn = {(1,0):'+x',(-1,0):'-x',(0,1):'+y',(0,-1):'-y'}[(round(dx), round(dy))]
    rows.append((e, dirn, st.median(h(x, zone) for x in g), st.median(h(x, block) for x in g), st.median(h(x, block) for x in pp),
                 st.median(p['pointer']['beta'] for p in r['predictions']), ex['position_error_mm']))
    print(f"ep {e} {dirn}: g-zone {rows[-1][2]:.0f} mm, g-block {rows[-1][3]:.0f}, p-block {rows[-1][4]:.0f}, beta {rows[-1][5]:.2f}, executed error {rows[-1][6]:.1f} mm", flush=True)
print('median g-zone %.0f, g-block %.0f, p-block %.0f, error %.1f mm' % tuple(st.median(r[i] for r in rows) for i in (2, 3, 4, 6)))
