"""Twenty-ninth session: the fox's inliers localized from the ground-truth pose, their keypoints as
detected and as aligned by the prototype (align.py): residuals at the ground truth and the pose
pycolmap refines from there on each. Usage, from the repository root (maps of a bench_accuracy workdir):

    MAP=fox-extrap-pl9 EVERY=2 PYTHONPATH=. python docs/benchmarks/s29-prototypes/fox_residuals.py
"""
import sys, os, numpy as np, pycolmap
from pathlib import Path
sys.argv = ["x"]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import align as A
from favormap.localize import Localizer
from favormap.io import read_sequence
from favormap.geometry import project, pose_error, to_rigid3d, from_rigid3d
mapn = os.environ.get("MAP", "fox-extrap")
WORK = os.environ.get("WORKDIR", "/tmp/acc28f")
loc = Localizer(f"{WORK}/{mapn}.h5")
data = loc.map.load()
src = data.provenance["source"]
seq = read_sequence(src)
names = set(data.frame_names)
A.MIN_NCC = float(os.environ.get("NCC", 0.8)); A.MAX_SHIFT = 2.0
opts = pycolmap.AbsolutePoseRefinementOptions(); opts.refine_focal_length = False; opts.refine_extra_params = False
qs = [f for f in seq.frames if f.name not in names]
if mapn == "orbit":
    seq = read_sequence(f"{WORK}/orbit_queries"); qs = seq.frames
rr, ra, er, ea = [], [], [], []
for fr in qs[:: int(os.environ.get("EVERY", 2))]:
    T = fr.cam_from_world
    r = loc.localize(fr.image_path, T, seq.cameras[fr.camera_id])
    inl = r.matches[r.inlier_mask]
    X = loc.positions[inl[:, 0]]; kp = r.keypoints[inl[:, 1]]
    moved, conv = A.align(loc, r.cam_from_world, r.camera.K, inl[:, 0], kp)
    al = np.where(conv[:, None], moved, kp)
    uv = project(r.camera.K, T, X)
    a, b = np.linalg.norm(kp - uv, axis=1), np.linalg.norm(al - uv, axis=1)
    def ref(u):
        ans = pycolmap.refine_absolute_pose(to_rigid3d(T), u.astype(np.float64), X.astype(np.float64), np.ones(len(u), bool), r.camera.to_pycolmap(), opts)
        return pose_error(from_rigid3d(ans["cam_from_world"]), T)[0]
    e1, e2 = ref(kp), ref(al)
    rr.append(a); ra.append(b); er.append(e1); ea.append(e2)
    dr, da = kp - uv, al - uv
    print(f"   mean residual raw ({dr[:,0].mean():+.2f},{dr[:,1].mean():+.2f}) aligned ({da[:,0].mean():+.2f},{da[:,1].mean():+.2f})")
    print(f"{fr.name}: conv {conv.mean():.2f} GT residual raw {np.median(a):.2f} aligned {np.median(b):.2f} (conv only raw {np.median(a[conv]):.2f} al {np.median(b[conv]):.2f}); refine from GT raw {e1:.5f} aligned {e2:.5f}", flush=True)
print("median GT residual raw %.2f aligned %.2f; errors raw %.5f aligned %.5f" % (np.median(np.concatenate(rr)), np.median(np.concatenate(ra)), np.median(er), np.median(ea)))
