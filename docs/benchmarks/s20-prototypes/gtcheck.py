import sys, pickle, numpy as np, os
sys.path.insert(0, '/work/main/tools')
import bench_accuracy as B
from pathlib import Path
from favormap.localize.baseline import StructureBaseline
from harness import d, centre
out = {}
for sp in B.fox_splits(["fox-extrap", "fox-holdout"]):
    base = StructureBaseline.build(sp.mapping, workdir=Path('/tmp/s20/base') / sp.name)
    ev = []
    for fr in sp.queries.frames:
        res = base.localize(fr.image_path, sp.queries.cameras[fr.camera_id])
        ev.append(centre(res.cam_from_world) - centre(fr.cam_from_world) if res.success else None)
    out[sp.name] = ev
    for seed in ("", "-s1", "-s2"):
        qs = d[sp.name + seed]
        cs = []; eb = []; ef = []
        for q, b in zip(qs, ev):
            if b is None: continue
            f = centre(q['est']) - centre(q['gt'])
            cs.append(f @ b / np.linalg.norm(f) / np.linalg.norm(b)); eb.append(np.linalg.norm(b)); ef.append(np.linalg.norm(f))
        cs = np.array(cs)
        print(f"{sp.name+seed:16s} baseline med {np.median(eb)*1e3:.2f} favormap {np.median(ef)*1e3:.2f}  cos(favormap err, baseline err): median {np.median(cs):.2f}  >0.5: {np.mean(cs>0.5):.2f}", flush=True)
pickle.dump(out, open('/tmp/s20/base_err.pkl', 'wb'))
