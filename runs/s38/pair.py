"""Session 38: SO-R against SO-Y, stack_blocks seeds 1000-1099, paired by seed (exact McNemar)."""
import json
from math import comb
def load(name):
    return {o['seed']: o['success'] for o in json.load(open(f'runs/s38/{name}/success.results.json'))['outcomes']}
y, r = load('so-y'), load('so-r')
common = sorted(set(y) & set(r))
a = sum(r[s] and not y[s] for s in common); b = sum(y[s] and not r[s] for s in common)
n = a + b
p = 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(min(a, b) + 1)) / 2 ** n)
print(f'SO-Y {sum(y[s] for s in common)}/{len(common)}  SO-R {sum(r[s] for s in common)}/{len(common)}  only SO-R {a}, only SO-Y {b}, exact p {p:.3f}')
