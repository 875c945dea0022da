"""All triangulated fox-extrap landmarks (before the 3,000 cap) and their error seen from the queries at GT."""
import os, sys, pickle, time
import numpy as np
sys.path.insert(0, "/work/main/tools")
os.environ.setdefault("FAVORMAP_FOX", "/work/shared/data/fox")
import bench_accuracy as ba
from favormap.build import BuildConfig, ExtractorSpec, extract_sequence, track_frames, triangulate_tracks
from favormap.geometry import project, camera_centers

split = sys.argv[1] if len(sys.argv) > 1 else "fox-extrap"
window = int(sys.argv[2]) if len(sys.argv) > 2 else 3
sp = ba.fox_splits([split])[0]
cfg = BuildConfig(match_window=window)
t = time.time()
ff = extract_sequence(sp.mapping, ExtractorSpec(cfg.extractor, cfg.max_keypoints), cfg.max_side)
tracks = track_frames(ff, cfg)
lms = triangulate_tracks(tracks, ff, cfg)
print("landmarks", len(lms), "time", time.time() - t)
# per-landmark track descriptors consistency
tr = lms.tracks
tid = tr.track_of_obs
D = np.stack([ff.features[f].descriptors[k] for f, k in zip(tr.frame_idx, tr.keypoint_idx)]).astype(np.float32)
mean = np.zeros((len(lms), D.shape[1]), np.float32)
np.add.at(mean, tid, D)
mean /= np.linalg.norm(mean, axis=1, keepdims=True)
cons = np.bincount(tid, np.einsum("ij,ij->i", D, mean[tid]), len(lms)) / tr.lengths
minc = np.full(len(lms), 2.0); np.minimum.at(minc, tid, np.einsum("ij,ij->i", D, mean[tid]))
maxre = np.zeros(len(lms)); np.maximum.at(maxre, tid, lms.reproj_errors)
C = camera_centers(ff.cam_from_world)
dist = np.linalg.norm(lms.positions[tid] - C[tr.frame_idx], axis=1)
depth = np.bincount(tid, dist, len(lms)) / tr.lengths
qf = extract_sequence(sp.queries, ExtractorSpec(cfg.extractor, 4096), cfg.max_side)
pairs = {k: [] for k in ("q", "lm", "d", "ang", "xy")}
vd = np.zeros((len(lms), 3)); np.add.at(vd, tid, (C[tr.frame_idx] - lms.positions[tid]) / dist[:, None]); vd /= np.linalg.norm(vd, axis=1, keepdims=True)
for i, f in enumerate(qf.features):
    T = qf.cam_from_world[i]
    uv, z = project(qf.cameras[i].K, T, lms.positions, with_depth=True)
    w, h = f.image_size
    vis = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h))
    d = np.linalg.norm(uv[vis, None] - f.keypoints[None].astype(np.float64), axis=2)
    sim = mean[vis] @ f.descriptors.T
    sim[d > 6] = -np.inf
    k = sim.argmax(1); rows = np.arange(len(vis)); ok = sim[rows, k] >= 0.85
    ray = camera_centers(T[None])[0] - lms.positions[vis[ok]]; ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    pairs["q"].append(np.full(ok.sum(), i)); pairs["lm"].append(vis[ok]); pairs["d"].append(d[rows, k][ok])
    pairs["xy"].append(f.keypoints[k[ok]].astype(np.float64)); pairs["ang"].append(np.degrees(np.arccos(np.clip((ray * vd[vis[ok]]).sum(1), -1, 1))))
pairs = {k: np.concatenate(v) for k, v in pairs.items()}
out = dict(n=len(lms), length=tr.lengths, angle=lms.angles_deg, mre=lms.mean_reproj_error, maxre=maxre,
           cons=cons, minc=minc, depth=depth, pairs=pairs, positions=lms.positions, view_dir=vd, qT=qf.cam_from_world, qK=np.stack([c.K for c in qf.cameras]), mT=ff.cam_from_world, mK=np.stack([c.K for c in ff.cameras]), obs_frame=tr.frame_idx, obs_xy=tr.xy, offsets=tr.offsets)
pickle.dump(out, open(f"/tmp/s20/lm-{split}-w{window}.pkl", "wb"))
print("pairs", len(pairs["d"]), "median", np.median(pairs["d"]), ">2px", np.mean(pairs["d"] > 2))
