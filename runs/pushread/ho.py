"""Teacher-forced push_buttons keyframes by sequence length and keyframe index: how many land
more than 6 cm from the expert's (buttons are at least 12 cm apart: another button)."""
import json, sys, collections
for f in sys.argv[1:]:
    d = json.load(open(f))
    c = collections.defaultdict(lambda: [0, 0])
    for k in d['per_keyframe']:
        if k['task'] != 'push_buttons': continue
        v = k['variation']; n = 1 if v < 20 else 2 if v < 35 else 3
        key = (n, k['keyframe'])
        c[key][1] += 1; c[key][0] += k['position_mm'] > 60
    print(f, ' '.join(f'{n}b@{i}:{a}/{b}' for (n, i), (a, b) in sorted(c.items())))
