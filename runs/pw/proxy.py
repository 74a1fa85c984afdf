import json,statistics as st,collections,sys
for f in sys.argv[1:]:
  d=json.load(open(f))
  by=collections.defaultdict(list); task=collections.defaultdict(list)
  for k in d['per_keyframe']:
    task[k['task']].append(k['position_mm'])
    if k['task']=='stack_blocks': by[k['keyframe']%6].append(k['position_mm'])
  print(f, 'median', round(d['model']['position_mm_median'],1), 'mean', round(d['model']['position_mm_mean'],1),
        'target', d['target_accuracy'], 'swap', round(d['instruction_swap_mm'],1),
        {t: round(st.median(v),1) for t,v in task.items()}, 'stack kinds', {k:round(st.median(v),1) for k,v in sorted(by.items())})
