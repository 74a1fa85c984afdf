"""Session 36 readout: PB5's stack_blocks with 40 keyframes against its 25-keyframe records."""
import collections, json
old = {}
for f in ['five-tasks-pb5.json', 'five-tasks-pb5-fresh.json']:
    for o in json.load(open('docs/results/' + f))['outcomes']:
        if o['task'] == 4:
            old[o['seed']] = o
new = {}
for seed in (1000, 1050):
    for o in json.load(open('runs/s36/budget/success%d.results.json' % seed))['outcomes']:
        new[o['seed']] = o
c = collections.defaultdict(lambda: [0, 0, 0, 0])  # n: [at 25 (record), at 25 (here), by 40, episodes]
mismatch = 0
for s, o in sorted(new.items()):
    n = o['variation'] % 3 + 2
    r = old[s]
    here25 = o['success'] and o['keyframes'] <= 25
    if here25 != r['success']:
        mismatch += 1
    c[n][0] += r['success']; c[n][1] += here25; c[n][2] += o['success']; c[n][3] += 1
print('blocks: record@25 / here@25 / here@40 of episodes')
for n in sorted(c):
    print(n, c[n])
t = [sum(v[i] for v in c.values()) for i in range(4)]
print('all', t, 'mismatches with the record at 25:', mismatch)
print('keyframes used by successes past 25:', sorted(o['keyframes'] for o in new.values() if o['success'] and o['keyframes'] > 25))
