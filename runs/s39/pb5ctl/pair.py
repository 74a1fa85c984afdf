"""Session 39: PB5's stack_blocks (seeds 1000-1099) with this session's controller (OSQP skipped where
no row is active) against PB5's record on this machine kind with session 35's binary (session 36),
paired by seed (exact McNemar)."""
import json
from math import comb
old = {}
for f in ['docs/results/five-tasks-pb5-s36.json', 'docs/results/five-tasks-pb5-s36-fresh.json']:
    d = json.load(open(f))
    si = d['tasks'].index('stack_blocks')
    old.update({o['seed']: o['success'] for o in d['outcomes'] if o['task'] == si})
new = {}
for i in (0, 1):
    new.update({o['seed']: o['success'] for o in json.load(open(f'runs/s39/pb5ctl/s{i}.results.json'))['outcomes']})
common = sorted(set(old) & set(new))
a = sum(new[s] and not old[s] for s in common); b = sum(old[s] and not new[s] for s in common)
n = a + b
p = 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, k) for k in range(min(a, b) + 1)) / 2 ** n)
print(f'new controller {sum(new[s] for s in common)}/{len(common)}, record {sum(old[s] for s in common)}/{len(common)}: only new {a}, only record {b}, exact p {p:.3f}')
