"""push_buttons successes by how many buttons the variation asks. Expert version 2 (session 35):
0-17 one, 18-33 two, 34-49 three; pass --v1 for records of version 1 (0-19, 20-34, 35-49).
usage: python3 runs/pb/buttons.py [--v1] RECORD..."""
import json, sys, collections
args = sys.argv[1:]
v1 = '--v1' in args
cuts = (20, 35) if v1 else (18, 34)
for f in [a for a in args if a != '--v1']:
    d = json.load(open(f)); ti = d['tasks'].index('push_buttons')
    c = collections.Counter(); n = collections.Counter()
    for o in d['outcomes']:
        if o['task'] != ti: continue
        k = 1 if o['variation'] < cuts[0] else 2 if o['variation'] < cuts[1] else 3
        n[k] += 1; c[k] += o['success']
    print(f, ' '.join(f'{k}-button {c[k]}/{n[k]}' for k in (1, 2, 3)), f'total {sum(c.values())}/{sum(n.values())}')
