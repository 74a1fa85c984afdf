"""Session 39: teacher-forced stack_blocks picks with no block within 3 cm of the prediction ("off"): distance to the expert's keyframe, the three nearest blocks (T named colour, D distractor), their spacing, z predicted and expert (cm, m)."""
import json, sys
for f in sys.argv[1:]:
    d = json.load(open(f)); rows=[]
    for k in d['per_keyframe']:
        i = k['keyframe']
        if i % 6: continue
        s = k['seed']
        I = json.load(open(f'runs/stackread/{"idle" if s < 1050 else "idle1070"}/{s}.json'))
        colour = I['objects'][0]['rgba']
        p = k['predicted_position']; e = k['expert_position']
        dx = lambda a,b: ((a[0]-b[0])**2+(a[1]-b[1])**2)**.5
        de = dx(p,e)
        objs = sorted((dx(p,o['position']), o['rgba']==colour, o['position']) for o in I['objects'])
        if objs[0][0] >= 0.03 and de >= 0.03:
            # between: distance from p to segment of two nearest blocks
            a=objs[0][2]; b=objs[1][2]
            rows.append((s,i,round(de*100,1),[ (round(o[0]*100,1), 'T' if o[1] else 'D') for o in objs[:3]], round(dx(a,b)*100,1), round(p[2],3), round(e[2],3)))
    for r in rows: print(r)
    print(len(rows))
