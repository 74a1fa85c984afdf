"""Session 41: arm SW against the shipped PB5, both evaluated here (machine C) by the same binary,
paired by seed per task (exact McNemar) and pooled over what both have finished; also each arm's
finished halves against PB5's records on machines A and B, for reference (not paired evidence:
other machines and binaries)."""
import glob, json, os
from math import comb, sqrt
def load(path):
    d = json.load(open(path))
    return {(d['tasks'][o['task']], o['seed']): o['success'] for o in d['outcomes']}
def mcnemar(a, b):
    n = a + b
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(min(a, b) + 1)) / 2 ** n)
def wilson(k, n, z=1.96):
    if n == 0: return (0, 0)
    p = k / n; c = (p + z*z/(2*n)) / (1 + z*z/n); h = z * sqrt(p*(1-p)/n + z*z/(4*n*n)) / (1 + z*z/n)
    return (100*(c-h), 100*(c+h))
arms = {}
for arm in ('sw', 'pb5'):
    arms[arm] = {}
    for f in sorted(glob.glob(f'runs/s41/eval/{arm}/*.[0-9]*[0-9].results.json')):
        arms[arm].update(load(f))
sw, pb = arms['sw'], arms['pb5']
rec = {}
for f in ('docs/results/five-tasks-pb5.json', 'docs/results/five-tasks-pb5-fresh.json'):
    rec.update(load(f))
recb = {}
for f in ('docs/results/five-tasks-pb5-s36.json', 'docs/results/five-tasks-pb5-s36-fresh.json'):
    recb.update(load(f))
A = B = 0
for task in ('stack_blocks', 'close_jar', 'slide_block', 'push_buttons', 'open_drawer'):
    common = sorted(k for k in set(sw) & set(pb) if k[0] == task)
    if not common:
        continue
    a = sum(sw[k] and not pb[k] for k in common); b = sum(pb[k] and not sw[k] for k in common)
    A += a; B += b
    ks, kp = sum(sw[k] for k in common), sum(pb[k] for k in common)
    n = len(common)
    ra = sum(rec[k] for k in common); rb = sum(recb[k] for k in common)
    lo, hi = wilson(ks, n); lo2, hi2 = wilson(kp, n)
    print(f'{task:13s} n={n:3d}  SW {ks:3d} ({lo:.0f}-{hi:.0f} %)  PB5 here {kp:3d} ({lo2:.0f}-{hi2:.0f} %)  only SW {a}, only PB5 {b}, exact p {mcnemar(a, b):.3f}   [PB5 records on these seeds: A {ra}, B {rb}]')
print(f'pooled: only SW {A}, only PB5 {B}, net {A - B:+d}, exact p {mcnemar(A, B):.3f}')
