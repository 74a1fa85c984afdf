"""Session 32: LA5 / LA5-1 against the shipped sampling of GUR / GUR1 (POST, POST1) on seeds 1000-1099, pooled."""
import json
from math import comb
def load(f):
    d = json.load(open(f)); return {(d['tasks'][o['task']], o['seed']): o['success'] for o in d['outcomes']}
def p_exact(a, b):
    n = a + b; k = min(a, b)
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(k + 1)) / 2 ** n)
pairs = {
    'LA5': [('docs/results/five-tasks-post.json', 'runs/la/la5/success1000.results.json'), ('docs/results/five-tasks-post-fresh.json', 'runs/la/la5/success1050.results.json')],
    'LA5-1': [('docs/results/five-tasks-post1.json', 'runs/la/la5-1/success1000.results.json'), ('docs/results/five-tasks-post1-fresh.json', 'runs/la/la5-1/success1050.results.json')],
}
tot = [0, 0]
for arm, ps in pairs.items():
    A = B = 0
    for base, new in ps:
        b, n = load(base), load(new)
        a_ = sum(1 for k in b if n[k] and not b[k]); b_ = sum(1 for k in b if b[k] and not n[k])
        print(arm, new.split('/')[-1], 'base', sum(b.values()), 'arm', sum(n.values()), f'{a_}/{b_} p={p_exact(a_, b_):.3g}')
        A += a_; B += b_
    print(arm, 'over 500:', f'{A}/{B} p={p_exact(A, B):.3g}')
    tot[0] += A; tot[1] += B
print('pooled over both draws (1000 pairs):', f'{tot[0]}/{tot[1]} p={p_exact(*tot):.3g}')
