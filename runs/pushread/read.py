"""Session 31: push_buttons' two- and three-button episodes: each policy keyframe that goes down
to a press (z below 0.80 m) matched to the expert's target buttons (T1, T2, T3 in the instructed
order, within 2 cm in xy) or to none (X: a distractor button or nowhere; its distance to the
nearest target in mm)."""
import json, sys, collections
name = sys.argv[1] if len(sys.argv) > 1 else 'flowram'
c = collections.Counter()
for s in range(1020, 1050):
    P = json.load(open(f'runs/pushread/{name}/{s}.json')); E = json.load(open(f'runs/pushread/expert/{s}.json'))
    targets = [a[:2] for a in E['actions'][1::2]][: (2 if s < 1035 else 3)]
    seq = []
    for a in P['actions']:
        if a[2] < 0.80:
            d = [((a[0] - t[0]) ** 2 + (a[1] - t[1]) ** 2) ** 0.5 for t in targets]
            k = min(range(len(d)), key=lambda i: d[i])
            seq.append(f'T{k + 1}' if d[k] < 0.02 else f'X{d[k] * 1000:.0f}')
    # collapse repeats
    col = [x for i, x in enumerate(seq) if i == 0 or x != seq[i - 1]]
    n = len(targets)
    want = [f'T{i + 1}' for i in range(n)]
    first_wrong = next((i for i in range(min(len(col), n)) if col[i] != want[i]), None)
    kind = 'ok' if P['success'] else (f'wrong at press {first_wrong + 1}: {col[first_wrong]}' if first_wrong is not None else 'short')
    c[(n, 'OK' if P['success'] else ('X' if first_wrong is not None and col[first_wrong].startswith('X') else 'T-order' if first_wrong is not None else 'short'), first_wrong)] += 1
    print(s, E['instruction'].replace('push the ', '').replace(' button', ''), 'OK ' if P['success'] else 'bad', P['keyframes'], ' '.join(col[:10]), '|', kind)
for k, v in sorted(c.items(), key=str): print(k, v)
