"""Session 30: stack_blocks readout with the scene. For each held-out seed: the policy's grasps
(gripper open -> closed) matched to the nearest of the six blocks' initial positions (idle run:
T = a target-colour block, D = a distractor; the number is the distance in mm when over 20), or
to the stack (S); its releases by level; and where the target blocks ended: on the platform's
footprint (within 25 mm of the stack's xy) at which levels, or off it."""
import json, sys, os, collections
name = sys.argv[1]
d = f'runs/stackread/{name}'
tot = collections.Counter()
fails = collections.Counter()
for s in range(1000, 1050):
    p, e, i = f'{d}/{s}.json', f'runs/stackread/expert4/{s}.json', f'runs/stackread/idle/{s}.json'
    if not all(os.path.exists(x) for x in (p, e, i)):
        continue
    P, E, I = json.load(open(p)), json.load(open(e)), json.load(open(i))
    n = int(P['instruction'].split()[1])
    ea = E['actions']
    stack = ea[3][:2]
    table_z = I['objects'][0]['position'][2]
    colour = I['objects'][0]['rgba']
    objs = [(o['name'], o['position'], 'T' if o['rgba'] == colour else 'D') for o in I['objects']]
    ev = []
    prev = 1.0
    for a in P['actions']:
        o = a[7]
        if prev > 0.5 and o < 0.5:
            ds = ((a[0] - stack[0]) ** 2 + (a[1] - stack[1]) ** 2) ** 0.5
            dist = [((a[0] - q[0]) ** 2 + (a[1] - q[1]) ** 2) ** 0.5 for _, q, _ in objs]
            k = min(range(len(objs)), key=lambda j: dist[j])
            if ds < min(dist) and ds < 0.02:
                tag = 'gS'
            else:
                tag = 'g' + objs[k][2] + objs[k][0][-1] + ('' if dist[k] < 0.02 else f'~{dist[k]*1000:.0f}')
            tot['grasp ' + (tag[:2] if '~' not in tag else tag[:2] + ' far')] += 1
            ev.append(tag)
        if prev < 0.5 and o > 0.5:
            ds = ((a[0] - stack[0]) ** 2 + (a[1] - stack[1]) ** 2) ** 0.5
            ev.append('r' + f'{(a[2] - ea[4][2]) / 0.04 + 1:.1f}' + ('' if ds < 0.015 else f'@{ds*1000:.0f}'))
        prev = o
    end = {o['name']: o['position'] for o in P['objects']}
    on = sorted(round((end[nm][2] - table_z) / 0.04, 1) for nm, _, c in objs if c == 'T'
                and ((end[nm][0] - stack[0]) ** 2 + (end[nm][1] - stack[1]) ** 2) ** 0.5 < 0.025)
    moved_off = sum(1 for nm, q, c in objs if ((end[nm][0] - q[0]) ** 2 + (end[nm][1] - q[1]) ** 2) ** 0.5 > 0.02
                    and ((end[nm][0] - stack[0]) ** 2 + (end[nm][1] - stack[1]) ** 2) ** 0.5 >= 0.025)
    ok = P['success']
    print(f"{s} n={n} {'OK ' if ok else 'bad'} kf={P['keyframes']:2d} end: on-platform levels {on} moved-elsewhere {moved_off} | " + ' '.join(ev))
    if not ok:
        fails[f'n={n} stacked {len(on)}'] += 1
print(dict(sorted(tot.items())))
print('failures by blocks on the platform at the end:', dict(sorted(fails.items())))
