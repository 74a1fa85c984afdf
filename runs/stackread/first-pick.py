import json, collections
c=collections.Counter()
for s in range(1000,1050):
    P,I=json.load(open(f'runs/stackread/post-end/{s}.json')),json.load(open(f'runs/stackread/idle/{s}.json'))
    colour=I['objects'][0]['rgba']
    objs=[(o['position'],o['rgba']==colour) for o in I['objects']]
    prev=1.0;k=0
    for a in P['actions']:
        o=a[7]
        if prev>0.5 and o<0.5:
            dist=[((a[0]-q[0])**2+(a[1]-q[1])**2)**.5 for q,_ in objs]
            j=min(range(6),key=lambda j:dist[j])
            tag=('T' if objs[j][1] else 'D')+('' if dist[j]<0.02 else '~')
            c[('first' if k==0 else 'later', tag)]+=1
            k+=1
        prev=o
print(sorted(c.items()))
