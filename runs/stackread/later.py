"""Session 31: teacher-forced stack_blocks picks (keyframe index mod 6 = 0, "above the next
block") on held-out episodes (seeds 1000-1009 and 1070-1099): the block nearest the prediction
in xy (starting layout from an idle run of the same seed): right = within 3 cm of the expert's,
T-other = another block of the named colour, D = a distractor (within 3 cm), off = none; first pick (index 0) against later picks (6, 12, 18)."""
import json, sys, collections
for f in sys.argv[1:]:
    d = json.load(open(f)); c = collections.Counter()
    for k in d['per_keyframe']:
        i = k['keyframe']
        if i % 6: continue
        s = k['seed']
        I = json.load(open(f'runs/stackread/{"idle" if s < 1050 else "idle1070"}/{s}.json'))
        colour = I['objects'][0]['rgba']
        p = k['predicted_position']
        dist = [(((p[0] - o['position'][0]) ** 2 + (p[1] - o['position'][1]) ** 2) ** 0.5, o['rgba'] == colour) for o in I['objects']]
        dm, t = min(dist)
        e = k['expert_position']
        right = ((p[0] - e[0]) ** 2 + (p[1] - e[1]) ** 2) ** 0.5 < 0.03
        kind = 'right' if right else ('T-other' if t else 'D') if dm < 0.03 else 'off'
        c[('first' if i == 0 else 'later', kind)] += 1
    print(f, dict(sorted(c.items())))
