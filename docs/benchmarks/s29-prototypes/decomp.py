"""Twenty-ninth session: where the orbit's shared half-pixel displacement comes from (synthetic room,
exact poses). Usage, from the repository root, with a tools/bench_accuracy.py --workdir DIR and a run's
rows (for the queries' angles); the last argument is the smallest angle to the mapping views (-1: all):

    PYTHONPATH=. python docs/benchmarks/s29-prototypes/decomp.py /tmp/acc28f \
        docs/benchmarks/accuracy-2026-11-28-s28-final.json.gz orbit.h5 -1

Surface points are found by casting the pixel's exact ray into the room (Open3D).
For each inlier (landmark X, query keypoint kp) at the ground-truth pose T:
 Pm = mean surface point of the landmark's mapping keypoints (each back-projected through its
      mapping view's true depth), Pq = the query keypoint back-projected through the query's depth.
Pose refined from T on: A (X, kp) as localized; B (Pm, kp): perfect triangulation of the mapping
detections, query detection as is; C (X, proj_T(Pm)): query detection consistent with the mapping
ones, landmark as is; E (Pm, proj_T(Pm)) ~ 0 (check)."""
import gzip, json, sys
import numpy as np, pycolmap
from favormap.geometry import from_rigid3d, to_rigid3d, pose_error, project, inverse
from favormap.io import read_sequence
from favormap.localize import Localizer
from favormap.synthetic import make_room
from favormap.synthetic.render import render_depth

d, run, mapname = sys.argv[1], sys.argv[2], sys.argv[3]
minang = float(sys.argv[4]) if len(sys.argv) > 4 else 40
rows = json.loads(gzip.decompress(open(run, "rb").read()))
row = next(r for r in rows if r["split"] == "orbit" and r["method"] == "rendered" and r["prior"] == "noise")
far = {q["name"]: q["angle_deg"] for q in row["per_query"] if q["angle_deg"] > minang}
scene = make_room(0)
seq = read_sequence(f"{d}/orbit_queries"); mseq = read_sequence(f"{d}/orbit_map")
loc = Localizer(f"{d}/{mapname}"); m = loc.map.load()
cam = mseq.cameras[0]; K = cam.K

def backproject(K, T, depth, uv):
    """exact ray cast through the sub-pixel position uv (pinhole, COLMAP pixel convention)"""
    from favormap.synthetic.render import _cast
    Tinv = inverse(T)
    ray_c = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)
    d = ray_c @ Tinv[:3, :3].T
    rays = np.concatenate([np.broadcast_to(Tinv[:3, 3], d.shape), d], 1).astype(np.float32)
    t, _ = _cast(scene, rays)
    return Tinv[:3, 3] + t[:, None] * d

# surface point of each landmark from its mapping observations
depths = {}
Pm = np.zeros((m.num_landmarks, 3)); spread = np.zeros(m.num_landmarks)
frames = np.asarray(m.track_frame)
for f in np.unique(frames):
    depths[f] = render_depth(scene, cam, m.cam_from_world[f])
P_obs = np.zeros((len(frames), 3))
for f in np.unique(frames):
    s = frames == f
    P_obs[s] = backproject(K, m.cam_from_world[f], depths[f], np.asarray(m.track_xy)[s])
lm = np.asarray(m.track_landmark)
for j in range(3):
    Pm[:, j] = np.bincount(lm, P_obs[:, j], m.num_landmarks) / np.bincount(lm, minlength=m.num_landmarks)
dev = np.linalg.norm(P_obs - Pm[lm], axis=1)
print(f"mapping detections' surface points: spread median {np.median(dev):.5f} u; landmark to Pm median "
      f"{np.median(np.linalg.norm(m.positions - Pm, axis=1)):.5f} u")
opts = pycolmap.AbsolutePoseRefinementOptions(); opts.refine_focal_length = False; opts.refine_extra_params = False
def refine(T, uv, X):
    ans = pycolmap.refine_absolute_pose(to_rigid3d(T), uv.astype(np.float64), X.astype(np.float64),
                                        np.ones(len(uv), bool), cam.to_pycolmap(), opts)
    return from_rigid3d(ans["cam_from_world"])
out = []
for fr in seq.frames:
    if fr.name not in far: continue
    T = fr.cam_from_world
    r = loc.localize(fr.image_path, T, seq.cameras[fr.camera_id])
    inl = r.matches[r.inlier_mask]
    X = loc.positions[inl[:, 0]]; kp = r.keypoints[inl[:, 1]]; P = Pm[inl[:, 0]]
    dq = render_depth(scene, cam, T); Pq = backproject(K, T, dq, kp)
    pP = project(K, T, P); pX = project(K, T, X)
    det = kp - pP; lme = pP - pX
    e = [pose_error(r.cam_from_world, T)[0]] + [pose_error(refine(T, a, b), T)[0] for a, b in
         ((kp, X), (kp, P), (pP, X), (kp, Pq))]
    out.append(e)
    print(f"{fr.name} {far[fr.name]:.0f} deg n {len(kp)}: |det| med {np.median(np.linalg.norm(det,axis=1)):.2f} px "
          f"mean vec ({det[:,0].mean():+.2f},{det[:,1].mean():+.2f}); |lm| med {np.median(np.linalg.norm(lme,axis=1)):.2f} px "
          f"mean vec ({lme[:,0].mean():+.2f},{lme[:,1].mean():+.2f}); err localized {e[0]:.5f}, refine(X,kp) {e[1]:.5f}, "
          f"(Pm,kp) {e[2]:.5f}, (X,proj Pm) {e[3]:.5f}, (Pq,kp) {e[4]:.6f}", flush=True)
o = np.array(out)
print("median errors: localized %.5f | (X,kp) %.5f | det only (Pm,kp) %.5f | landmark only (X,proj Pm) %.5f | check %.6f" % tuple(np.median(o, 0)))
