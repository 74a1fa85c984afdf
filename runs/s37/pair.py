"""Session 37: an arm's per-task records (runs/s37/<arm>/<task>.<seed>.results.json) paired with
PB5's record on this machine kind (runs/s36/pb5-here, session 35's binary): successes per task,
only-arm / only-PB5, exact McNemar p."""
import json, sys, glob
from math import comb
TASKS = ['open_drawer', 'push_buttons', 'slide_block', 'close_jar', 'stack_blocks']
def p_exact(a, b):
    n = a + b
    if n == 0:
        return 1.0
    return min(1.0, 2 * sum(comb(n, i) for i in range(min(a, b) + 1)) / 2 ** n)
base = {}
for seed in (1000, 1050):
    for o in json.load(open(f'runs/s36/pb5-here/success{seed}.results.json'))['outcomes']:
        base[(TASKS[o['task']], o['seed'])] = o['success']
arm = sys.argv[1]
tot = [0, 0, 0, 0, 0]
for name in TASKS:
    here = {}
    for f in glob.glob(f'runs/s37/{arm}/{name}.*.results.json'):
        if '.s0.' in f or '.s1.' in f:
            continue
        for o in json.load(open(f))['outcomes']:
            here[(name, o['seed'])] = o['success']
    if not here:
        continue
    h = sum(here.values()); o = sum(base[k] for k in here)
    a = sum(here[k] and not base[k] for k in here); b = sum(base[k] and not here[k] for k in here)
    print(f'{name:13s} {arm} {h}/{len(here)}  PB5 {o}/{len(here)}  only {arm} {a}, only PB5 {b}, exact p {p_exact(a, b):.3f}')
    for i, v in enumerate([h, o, a, b, len(here)]):
        tot[i] += v
h, o, a, b, n = tot
print(f'all           {arm} {h}/{n}  PB5 {o}/{n}  only {arm} {a}, only PB5 {b}, exact p {p_exact(a, b):.3f}')
