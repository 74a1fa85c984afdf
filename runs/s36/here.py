"""Session 36: the shipped checkpoint (PB5) re-evaluated on this machine against its records
(session 35's machine): per-task successes, and the episodes whose outcome differs."""
import json, sys
from math import comb
TASKS = ['open_drawer', 'push_buttons', 'slide_block', 'close_jar', 'stack_blocks']
def load(path):
    return {(o['task'], o['seed']): o['success'] for o in json.load(open(path))['outcomes']}
def p_exact(a, b):
    n = a + b
    if n == 0:
        return 1.0
    k = min(a, b)
    return min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2 ** n)
rows = []
for seed, rec in [(1000, 'five-tasks-pb5.json'), (1050, 'five-tasks-pb5-fresh.json')]:
    try:
        here = load('runs/s36/pb5-here/success%d.results.json' % seed)
    except FileNotFoundError:
        continue
    old = load('docs/results/' + rec)
    rows.append((seed, here, old))
tot = [0, 0, 0, 0, 0]
for t, name in enumerate(TASKS):
    h = o = a = b = n = 0
    for seed, here, old in rows:
        for k in here:
            if k[0] != t:
                continue
            n += 1; h += here[k]; o += old[k]
            a += here[k] and not old[k]; b += old[k] and not here[k]
    print(f'{name:13s} here {h}/{n}  record {o}/{n}  only here {a}, only record {b}')
    for i, v in enumerate([h, o, a, b, n]):
        tot[i] += v
h, o, a, b, n = tot
print(f'all           here {h}/{n}  record {o}/{n}  only here {a}, only record {b}, exact p {p_exact(a, b):.2f}; outcomes differing {a + b} of {n}')
