"""Session 35: PB5 / PB5-1 against LP5 / LP5-1 on the corrected push_buttons, seeds 1000-1099
per task, pooled over both draws (the registered rule); per task over both draws. The baselines
are LP5's / LP5-1's records with push_buttons' outcomes replaced by their re-evaluation on
expert version 2 (runs/pb/lp5-push, runs/pb/lp5-1-push); the other four tasks did not change.
usage: python3 runs/pb/pool.py"""
import json, os, collections
from math import comb

def load(f):
    d = json.load(open(f))
    return {(d['tasks'][o['task']], o['seed']): o['success'] for o in d['outcomes']}

def p_exact(a, b):
    n = a + b; k = min(a, b)
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2 ** n)

def baseline(old, push):
    b = load(old); p = load(push)
    assert all(k[0] == 'push_buttons' for k in p)
    assert {k for k in b if k[0] == 'push_buttons'} == set(p), 'push seeds differ'
    b.update(p)
    return b

pairs = {
    'PB5': [(('docs/results/five-tasks-lp5.json', 'runs/pb/lp5-push/success1000.results.json'), 'runs/pb/pb5/success1000.results.json'),
            (('docs/results/five-tasks-lp5-fresh.json', 'runs/pb/lp5-push/success1050.results.json'), 'runs/pb/pb5/success1050.results.json')],
    'PB5-1': [(('docs/results/five-tasks-lp5-1.json', 'runs/pb/lp5-1-push/success1000.results.json'), 'runs/pb/pb5-1/success1000.results.json'),
              (('docs/results/five-tasks-lp5-1-fresh.json', 'runs/pb/lp5-1-push/success1050.results.json'), 'runs/pb/pb5-1/success1050.results.json')],
}
tot = [0, 0]; task = collections.defaultdict(lambda: [0, 0, 0, 0])
for arm, pp in pairs.items():
    A = B = 0
    for (old, push), new in pp:
        if not (os.path.exists(new) and os.path.exists(push)):
            print(arm, new, 'missing'); continue
        b, n = baseline(old, push), load(new)
        assert set(b) == set(n), 'different episodes'
        a_ = sum(1 for k in b if n[k] and not b[k]); b_ = sum(1 for k in b if b[k] and not n[k])
        per = collections.Counter(k[0] for k in n if n[k]); perb = collections.Counter(k[0] for k in b if b[k])
        print(arm, new.split('/')[-1], 'base', sum(b.values()), 'arm', sum(n.values()), f'{a_}/{b_} p={p_exact(a_, b_):.3g}', 'arm', dict(per), 'base', dict(perb))
        for k in b:
            t = task[k[0]]; t[0] += n[k] and not b[k]; t[1] += b[k] and not n[k]; t[2] += b[k]; t[3] += n[k]
        A += a_; B += b_
    print(arm, 'over 500:', f'{A}/{B} p={p_exact(A, B):.3g}')
    tot[0] += A; tot[1] += B
print('pooled over both draws:', f'{tot[0]}/{tot[1]} p={p_exact(*tot):.3g}')
for t, (a, b, nb, nn) in task.items():
    print(f'  {t}: base {nb} arm {nn}  only arm / only base {a}/{b} p={p_exact(a, b):.3g}')
