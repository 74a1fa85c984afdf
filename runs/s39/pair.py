"""Session 39: arm PS (pointer_sigma 0.01) against session 38's SO-Y, draw by draw (PS / SO-Y,
PS-1 / SO-Y1), stack_blocks seeds 1000-1099, paired by seed (exact McNemar), and pooled."""
import json, os
from math import comb
def load(path):
    return {o['seed']: o['success'] for o in json.load(open(f'{path}/success.results.json'))['outcomes']}
def mcnemar(a, b):
    n = a + b
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(min(a, b) + 1)) / 2 ** n)
A = B = 0
for new, old in [('runs/s39/ps', 'runs/s38/so-y'), ('runs/s39/ps-1', 'runs/s38/so-y1')]:
    if not os.path.exists(f'{new}/success.results.json'):
        continue
    x, y = load(new), load(old)
    common = sorted(set(x) & set(y))
    a = sum(x[s] and not y[s] for s in common); b = sum(y[s] and not x[s] for s in common)
    A += a; B += b
    print(f'{new} {sum(x[s] for s in common)}/{len(common)}  {old} {sum(y[s] for s in common)}/{len(common)}  only new {a}, only old {b}, exact p {mcnemar(a, b):.3f}')
print(f'pooled: only PS {A}, only SO-Y {B}, net {A - B:+d}, exact p {mcnemar(A, B):.3f}')
