"""Session 34: CF5 / CF5-1 against the shipped LP5 / LP5-1 records on seeds 1000-1099, pooled (the registered rule);
per task over both draws. usage: python3 runs/cf/pool.py [run0 run1]"""
import json, os, sys, collections
from math import comb
def load(f):
    d = json.load(open(f)); return {(d['tasks'][o['task']], o['seed']): o['success'] for o in d['outcomes']}
def p_exact(a, b):
    n = a + b; k = min(a, b)
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2 ** n)
d0, d1 = (sys.argv[1], sys.argv[2]) if len(sys.argv) > 2 else ('runs/cf/cf5', 'runs/cf/cf5-1')
ps = {'CF5': [('docs/results/five-tasks-lp5.json', f'{d0}/success1000.results.json'), ('docs/results/five-tasks-lp5-fresh.json', f'{d0}/success1050.results.json')],
      'CF5-1': [('docs/results/five-tasks-lp5-1.json', f'{d1}/success1000.results.json'), ('docs/results/five-tasks-lp5-1-fresh.json', f'{d1}/success1050.results.json')]}
tot = [0, 0]; task = collections.defaultdict(lambda: [0, 0, 0, 0])
for arm, pp in ps.items():
    A = B = 0
    for base, new in pp:
        if not os.path.exists(new): print(arm, new, 'missing'); continue
        b, n = load(base), load(new)
        assert set(b) == set(n), 'different episodes'
        a_ = sum(1 for k in b if n[k] and not b[k]); b_ = sum(1 for k in b if b[k] and not n[k])
        per = collections.Counter(k[0] for k in n if n[k])
        print(arm, new.split('/')[-1], 'base', sum(b.values()), 'arm', sum(n.values()), f'{a_}/{b_} p={p_exact(a_, b_):.3g}', dict(per))
        for k in b:
            t = task[k[0]]; t[0] += n[k] and not b[k]; t[1] += b[k] and not n[k]; t[2] += b[k]; t[3] += n[k]
        A += a_; B += b_
    print(arm, 'over 500:', f'{A}/{B} p={p_exact(A, B):.3g}')
    tot[0] += A; tot[1] += B
print('pooled over both draws:', f'{tot[0]}/{tot[1]} p={p_exact(*tot):.3g}')
for t, (a, b, nb, nn) in task.items():
    print(f'  {t}: base {nb} arm {nn}  only arm / only base {a}/{b} p={p_exact(a, b):.3g}')
