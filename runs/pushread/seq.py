"""Teacher-forced proxy for push_buttons' sequences (held_push_sequences): for each keyframe of
the stages after the first (index 2-5), which instructed button the prediction lands on (within
3 cm in xy of that button's press keyframe) against the expert's; 'order' counts predictions on
another instructed button, 'off' those on none."""
import json, sys, collections
print('arm: 2 buttons right/order/off (index 2-3) | 3 buttons right/order/off (index 2-5) | all median mm')
for f in sys.argv[1:]:
    d = json.load(open(f))
    eps = collections.defaultdict(dict)
    for k in d['per_keyframe']:
        eps[(k['seed'], k['variation'])][k['keyframe']] = k
    c = {2: [0, 0, 0], 3: [0, 0, 0]}
    i2t3 = i4t1 = 0
    for (seed, v), ks in eps.items():
        n = 2 if v < 35 else 3
        presses = [ks[i]['expert_position'][:2] for i in range(1, 2 * n, 2)]
        for i in range(2, 2 * n):
            if i not in ks: continue
            p = ks[i]['predicted_position'][:2]; want = (i // 2)
            dist = [((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2) ** 0.5 for q in presses]
            j = min(range(n), key=lambda j: dist[j])
            c[n][0 if (dist[j] < 0.03 and j == want) else 1 if dist[j] < 0.03 else 2] += 1
            if n == 3 and dist[j] < 0.03:
                i2t3 += (i == 2 and j == 2); i4t1 += (i == 4 and j == 0)
    print(f.split('/')[-1], '2b', '/'.join(map(str, c[2])), '| 3b', '/'.join(map(str, c[3])), '|', round(d['model']['position_mm_median'], 1), '| idx2->T3', i2t3, 'idx4->T1', i4t1)
