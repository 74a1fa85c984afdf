"""Writes a copy of GUR's checkpoint whose config sets flow.pointer_sharpening (json), with
trainer.json's recorded size and FNV-1a of config.json updated."""
import json, os, sys
name, sharp = sys.argv[1], json.loads(sys.argv[2])
src = 'runs/gu/gur/checkpoints/step-000014000'
D = f'runs/stackread/{name}/checkpoints/step-000014000'
os.makedirs(D, exist_ok=True)
for f in ['ema.safetensors', 'model.safetensors', 'optimizer.safetensors']:
    if not os.path.exists(f'{D}/{f}'):
        os.link(f'{src}/{f}', f'{D}/{f}')
open(f'runs/stackread/{name}/checkpoints/latest', 'w').write(open('runs/gu/gur/checkpoints/latest').read())
d = json.loads(open(f'{src}/config.json').read())
d['flow']['pointer_sharpening'] = sharp
b = json.dumps(d, indent=2).encode()
h = 0xcbf29ce484222325
for c in b:
    h ^= c; h = (h * 0x100000001b3) & 0xffffffffffffffff
open(f'{D}/config.json', 'wb').write(b)
t = json.load(open(f'{src}/trainer.json'))
t['files']['config.json'] = {'bytes': len(b), 'fnv1a64': '%016x' % h}
json.dump(t, open(f'{D}/trainer.json', 'w'), indent=2)
