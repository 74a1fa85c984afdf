"""Session 39: median and mean position error (predicted - expert, mm, world frame) per keyframe kind (index mod 6) and first pick or later, from bench heldout --json."""
import json, sys, statistics as st
for f in sys.argv[1:]:
    d = json.load(open(f))
    byk = {}
    for k in d['per_keyframe']:
        i = k['keyframe']; m = i % 6; first = i < 6
        p = k['predicted_position']; e = k['expert_position']
        byk.setdefault((m, first), []).append([p[j]-e[j] for j in range(3)])
    for key in sorted(byk):
        v = byk[key]
        print(f.split('/')[-2], key, len(v), [round(st.median(x[j] for x in v)*1000,1) for j in range(3)], 'mean', [round(st.mean(x[j] for x in v)*1000,1) for j in range(3)], 'medianabs', round(st.median((x[0]**2+x[1]**2+x[2]**2)**.5 for x in v)*1000,1))
