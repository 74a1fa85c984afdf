#!/usr/bin/env python3
"""Pointer readouts on two-button push_buttons episodes (runs/goal/held_push_seq, seeds 1020-1029):
readout_push.py CHECKPOINT. At keyframe 0 (going to the first button): where g and p point."""
import json, subprocess, sys, statistics as st, math
import os
B = os.environ.get('FLOWRAM', 'target/release/flowram')  # run from the repository root
ck = sys.argv[1]
def rec(ep, k):
    return json.loads(subprocess.run([B, 'predict', '--checkpoint', ck, '--episode', ep, '--keyframe', str(k), '--samples', '8', '--json'], capture_output=True, text=True, check=True).stdout)
h = lambda a, b: math.hypot(a[0]-b[0], a[1]-b[1]) * 1000
rows = []
for e in range(10):
    ep = f'runs/goal/held_push_seq/episode_{e:05d}.safetensors'
    r0 = rec(ep, 0); first = r0['recorded']['position']; second = rec(ep, 2)['recorded']['position']
    ex = r0['predictions'][r0['executed']]
    g = st.median(h(p['pointer']['goal'], first) for p in r0['predictions']), st.median(h(p['pointer']['goal'], second) for p in r0['predictions'])
    pp = st.median(h(p['pointer']['pointed'], first) for p in r0['predictions']), st.median(h(p['pointer']['pointed'], second) for p in r0['predictions'])
    near_first = sum(h(p['keyframe']['position'], first) < h(p['keyframe']['position'], second) for p in r0['predictions'])
    print(f"ep {e}: g to 1st/2nd {g[0]:.0f}/{g[1]:.0f} mm, p to 1st/2nd {pp[0]:.0f}/{pp[1]:.0f}, samples nearer the 1st {near_first}/8, executed to 1st {h(ex['keyframe']['position'], first):.0f} mm", flush=True)
