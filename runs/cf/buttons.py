"""push_buttons successes by how many buttons the variation asks (0-19: one, 20-34: two, 35-49: three)."""
import json, sys, collections
for f in sys.argv[1:]:
    d = json.load(open(f)); ti = d['tasks'].index('push_buttons')
    c = collections.Counter(); n = collections.Counter()
    for o in d['outcomes']:
        if o['task'] != ti: continue
        k = 1 if o['variation'] < 20 else 2 if o['variation'] < 35 else 3
        n[k] += 1; c[k] += o['success']
    print(f, ' '.join(f'{k}-button {c[k]}/{n[k]}' for k in (1, 2, 3)))
