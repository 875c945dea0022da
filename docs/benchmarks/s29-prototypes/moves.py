"""Twenty-ninth session: how far the alignment moves the inliers' keypoints (localized from the ground
truth) and whether the moves share a direction, on the first 8 queries of a map of a bench_accuracy
workdir:  WORKDIR=/tmp/acc29f PYTHONPATH=. python docs/benchmarks/s29-prototypes/moves.py fox-holdout"""
import os
import numpy as np, sys
WORK = os.environ.get("WORKDIR", "/tmp/acc29f")
from favormap.localize import Localizer, LocalizeConfig
from favormap.localize.align import blurred_gray
from favormap.io import read_sequence
name = sys.argv[1]
loc = Localizer(f"{WORK}/{name}.h5", LocalizeConfig(align=True))
al = loc._aligner
data_names = set(loc.map.frame_names)
if name.startswith("orbit"):
    seq = read_sequence(WORK + "/orbit_queries"); qs = seq.frames[:8]
else:
    seq = read_sequence("/work/shared/data/fox"); qs = [f for f in seq.frames if f.name not in data_names][:8]
for fr in qs:
    T = fr.cam_from_world
    r = loc.localize(fr.image_path, T, seq.cameras[fr.camera_id])
    inl = r.matches[r.inlier_mask]
    img, cam = loc.prepare(fr.image_path, seq.cameras[fr.camera_id])
    kp = r.keypoints[inl[:, 1]].astype(float)
    moved, ok = al.align(blurred_gray(img, 1.0), cam.K, T, loc.positions, inl[:, 0], kp)
    d = (moved - kp)[ok]
    print(f"{fr.name}: conv {ok.mean():.2f} |move| median {np.median(np.linalg.norm(d, axis=1)):.2f} mean vec ({d[:,0].mean():+.2f},{d[:,1].mean():+.2f})")
