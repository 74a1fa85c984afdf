"""Session 43: arm SG (session 43) against the shipped PB5 on stack_blocks, both evaluated on machine C by binaries
with the same inference code, paired by seed (exact McNemar), over what SG has finished."""
import glob, json, sys
sys.path.insert(0, 'runs/s41')
from math import comb, sqrt
def load(arm):
    r = {}
    for f in sorted(glob.glob(f'runs/s41/eval/{arm}/stack_blocks.*.results.json')):
        if '.s0.' in f or '.s1.' in f: continue
        d = json.load(open(f)); r.update({o['seed']: o['success'] for o in d['outcomes']})
    return r
def mcnemar(a, b):
    n = a + b
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, i) for i in range(min(a, b) + 1)) / 2 ** n)
def wilson(k, n, z=1.96):
    p = k / n; c = (p + z*z/(2*n)) / (1 + z*z/n); h = z * sqrt(p*(1-p)/n + z*z/(4*n*n)) / (1 + z*z/n)
    return (100*(c-h), 100*(c+h))
sg, pb = load('sg'), load('pb5')
common = sorted(set(sg) & set(pb))
if not common: sys.exit('no SG episodes yet')
a = sum(sg[s] and not pb[s] for s in common); b = sum(pb[s] and not sg[s] for s in common)
kg, kp, n = sum(sg[s] for s in common), sum(pb[s] for s in common), len(common)
print(f'stack_blocks n={n}  SG {kg} ({wilson(kg,n)[0]:.0f}-{wilson(kg,n)[1]:.0f} %)  PB5 here {kp} ({wilson(kp,n)[0]:.0f}-{wilson(kp,n)[1]:.0f} %)  only SG {a}, only PB5 {b}, net {a-b:+d}, exact p {mcnemar(a,b):.3f}')
