import json, os, collections
c = collections.Counter()
for name in ['post-end','gur-end']:
  d=f'runs/stackread/{name}'
  if not os.path.isdir(d): continue
  for s in range(1000,1050):
    p,i=f'{d}/{s}.json',f'runs/stackread/idle/{s}.json'
    if not (os.path.exists(p) and os.path.exists(i)): continue
    P,I=json.load(open(p)),json.load(open(i))
    colour=I['objects'][0]['rgba']
    objs=[(o['name'],o['position'],o['rgba']==colour) for o in I['objects']]
    targets=sorted([q for _,q,t in objs if t], key=lambda q:q[1])
    prev=1.0; k=0
    for a in P['actions']:
      o=a[7]
      if prev>0.5 and o<0.5:
        dist=[((a[0]-q[0])**2+(a[1]-q[1])**2)**.5 for _,q,_ in objs]
        j=min(range(6),key=lambda j:dist[j])
        if dist[j]<0.02:
          if k>0 and k<len(targets):
            exp=targets[k]; prevt=targets[k-1]
            nm,q,t=objs[j]
            if not t:
              c[(name,'D between prev and expected' if prevt[1]<q[1]<exp[1] else ('D left of expected' if q[1]>exp[1] else 'D right of prev'))]+=1
            else:
              c[(name,'T expected' if abs(q[1]-exp[1])<1e-6 else 'T other')]+=1
          k+=1
      prev=o
for kk,v in sorted(c.items()): print(kk,v)
