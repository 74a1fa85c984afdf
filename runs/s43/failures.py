"""Reads runs/s43/fail/{arm}_{seed}.json against expert_{seed}.json: per failed stack_blocks
episode, the blocks asked for, picks (gripper closing), releases and their horizontal distance
from the platform centre, the final state of the target-colour blocks (on the footprint within
2.5 cm, level) and a failure class.
  python3 runs/s43/failures.py [arm]"""
import json, sys, glob, math, collections
arm = sys.argv[1] if len(sys.argv) > 1 else 'pb5'
TABLE_Z, TOP, SIZE = 0.75, 0.005, 0.04
rows = []
for path in sorted(glob.glob(f'runs/s43/fail/{arm}_*.json')):
    seed = int(path.rsplit('_', 1)[1].split('.')[0])
    try:
        run = json.load(open(path)); exp = json.load(open(f'runs/s43/fail/expert_{seed}.json'))
    except Exception:
        continue
    count = run['variation'] % 3 + 2
    centre = exp['actions'][3][:2]  # the expert's "above the stack"
    colour = exp['objects'][0]['rgba']
    acts = run['actions']
    picks = sum(1 for a, b in zip([[1.0]] + acts, acts) if a[-1] > 0.5 and b[-1] < 0.5)
    releases = [b for a, b in zip(acts, acts[1:]) if a[-1] < 0.5 and b[-1] > 0.5]
    rel_d = [1e3 * math.dist(r[:2], centre) for r in releases]
    rel_on = [d for d in rel_d if d < 60]  # releases over the stack
    final = []
    for o in run['objects'][:4]:
        d = 1e3 * math.dist(o['position'][:2], centre)
        lvl = max(0, math.floor((o['position'][2] - TABLE_Z - TOP) / SIZE))
        final.append((round(d), lvl))
    on = sorted(l for d, l in final if d < 25)
    near = sorted((d, l) for d, l in final if 25 <= d < 60)
    wrong_on = [o['name'] for o in run['objects'][4:] if 1e3 * math.dist(o['position'][:2], centre) < 40]
    # classes
    first_bad_release = next((i for i, d in enumerate(rel_on) if d >= 20), None)
    if len(rel_on) < count and len(acts) >= 25:
        klass = 'budget' if count == 4 and len(rel_on) >= count - 1 else 'few-releases'
    else:
        klass = 'placed-but-not-counted'
    if wrong_on:
        klass += '+distractor-on-stack'
    rows.append(dict(seed=seed, count=count, keyframes=len(acts), picks=picks, releases_on_stack=len(rel_on),
                     release_mm=[round(d) for d in rel_on], final_on=on, final_near=near, wrong_on=wrong_on,
                     klass=klass, success=run['success']))
for r in rows:
    print(r)
c = collections.Counter(r['klass'] for r in rows)
print(arm, len(rows), 'episodes;', dict(c))
print('reproduced as failures:', sum(not r['success'] for r in rows), 'of', len(rows))
allrel = [d for r in rows for d in r['release_mm']]
if allrel:
    allrel.sort(); print('release distance from centre mm: median', allrel[len(allrel)//2], 'p90', allrel[int(.9*len(allrel))], 'n', len(allrel))

# Final state per failure: consecutive counted levels from 0 (the success rule's), target blocks
# 25-60 mm from the centre (off the footprint: placed off-centre or fallen), distractors on it.
print('\nseed count | levels stacked (rule) | targets near but off | distractor on | releases over stack | picks')
tab = collections.Counter()
for r in rows:
    lv = 0
    while lv in r['final_on']:
        lv += 1
    short = r['count'] - lv
    near = len(r['final_near'])
    key = ('short %d' % short, 'off-footprint' if near else '-', 'distractor' if r['wrong_on'] else '-')
    tab[key] += 1
    print(r['seed'], r['count'], '|', lv, r['final_on'], '|', r['final_near'], '|', r['wrong_on'], '|', r['releases_on_stack'], r['release_mm'], '|', r['picks'])
print()
for k, v in sorted(tab.items()):
    print(v, k)

# Distractors picked or knocked: moved more than 3 cm from where the expert (which never touches
# them) leaves them; and within 4 / 6 cm of the platform's centre at the end.
moved = d40 = d60 = 0
for r in rows:
    run = json.load(open(f"runs/s43/fail/{arm}_{r['seed']}.json"))
    exp = json.load(open(f"runs/s43/fail/expert_{r['seed']}.json"))
    centre = exp['actions'][3][:2]
    start = {o['name']: o['position'] for o in exp['objects']}
    ds = [1e3 * math.dist(o['position'][:2], centre) for o in run['objects'][4:]]
    d40 += any(x < 40 for x in ds); d60 += any(x < 60 for x in ds)
    moved += any(1e3 * math.dist(o['position'][:2], start[o['name']][:2]) > 30 for o in run['objects'][4:])
print(f'{arm}: of {len(rows)} failures, a distractor moved > 3 cm in {moved}; within 4 cm of the centre {d40}, 6 cm {d60}')
