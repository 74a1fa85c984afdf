"""Paired per-task table of two or more success records: successes, and for each record after
the first, only-it / only-first with the exact McNemar p."""
import json, sys
from math import comb
def p_exact(a, b):
    n = a + b
    if n == 0: return 1.0
    k = min(a, b)
    return min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2 ** n)
def load(f):
    d = json.load(open(f))
    return {(d['tasks'][o['task']], o['seed']): o['success'] for o in d['outcomes']}, d['tasks']
recs = [load(f) for f in sys.argv[1:]]
base, tasks = recs[0]
tot = [[0, 0] for _ in recs]
for t in tasks + ['all']:
    row = [t]
    for i, (r, _) in enumerate(recs):
        keys = [k for k in base if t == 'all' or k[0] == t]
        s = sum(r[k] for k in keys)
        if i == 0:
            row.append(str(s))
        else:
            a = sum(1 for k in keys if r[k] and not base[k]); b = sum(1 for k in keys if base[k] and not r[k])
            row.append(f'{s} ({a}/{b} p={p_exact(a, b):.3g})')
    print(' | '.join(row))
