"""What would perfect matching give on this map? Correspondences chosen with the true pose (each landmark
visible from it paired with the detected query keypoint nearest its true projection, mutually, within R px),
refined by the localizer's final step (estimate_noise) from the true pose; the same step on each variant's
own inliers calibrates the procedure. The control ("random"): uniformly random points, as many as the query's
keypoints, chosen the same way: what choosing by the true pose alone gives."""
import sys, dataclasses as dc, numpy as np
from pathlib import Path
from scipy.spatial import cKDTree
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B
from favormap.localize import Localizer, make_source
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.localize.refine import estimate_noise, landmark_covariances
from favormap.visibility import visible_rows
from favormap.geometry import project, pose_error
from favormap.mapfile import Map

path = Path(sys.argv[1])
split = B.fox_splits(["fox-extrap"])[0]
m = Map.open(path)
priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
locs = {s: Localizer(m, dc.replace(B.localizer_config({}), descriptors=s), descriptor_source=make_source(s, m, "cpu", None)) for s in ("rendered", "mean")}
rows_out = []
def refine(loc, gt, K, lm, kp):
    cov = landmark_covariances(m, lm, loc._landmark_sigma(lm))
    T, _, _ = estimate_noise(gt, loc.positions[lm], kp, K, cov, loc.config.keypoint_sigma_px)
    return pose_error(T, gt)[0]
for i, fr in enumerate(split.queries.frames):
    cam0 = split.queries.cameras[fr.camera_id]
    gt = fr.cam_from_world
    row = {}
    feats = None
    for s, loc in locs.items():
        res = loc.localize(fr.image_path, priors[i], cam0)
        row[s] = pose_error(res.cam_from_world, gt)[0] if res.success else np.inf
        inl = res.matches[res.inlier_mask]
        row[s + "-set"] = set(inl[:, 0].tolist())
        row[s + "-refit"] = refine(loc, gt, res.camera.K, inl[:, 0], res.keypoints[inl[:, 1]])
        if feats is None:
            img, cam = loc.prepare(fr.image_path, cam0)
            feats = loc.extractor.extract(img)
    loc = locs["rendered"]
    vis = visible_rows(loc.index, cam, gt, m.view_dir, m.view_angle, m.depth_range, loc.config.view_limits)
    uv = project(cam.K, gt, loc.positions[vis])
    kp = np.asarray(feats.keypoints, np.float64)
    d1, j1 = cKDTree(kp).query(uv)
    d2, j2 = cKDTree(uv).query(kp)
    rng = np.random.default_rng(i)
    kpr = rng.uniform([0, 0], [cam.width, cam.height], size=kp.shape)
    d1r, j1r = cKDTree(kpr).query(uv)
    d2r, j2r = cKDTree(uv).query(kpr)
    for R in (2.0, 4.0):
        ok = (d1r < R) & (j2r[j1r] == np.arange(len(uv)))
        row[f"random{R:g}"] = refine(loc, gt, cam.K, vis[ok], kpr[j1r[ok]])
        row[f"random{R:g}-n"] = int(ok.sum())
    for R in (1.0, 2.0, 4.0):
        ok = (d1 < R) & (j2[j1] == np.arange(len(uv)))
        row[f"oracle{R:g}"] = refine(loc, gt, cam.K, vis[ok], kp[j1[ok]])
        row[f"oracle{R:g}-n"] = int(ok.sum())
    a, b = row["rendered-set"], row["mean-set"]
    row["jaccard"] = len(a & b) / max(len(a | b), 1)
    print(i, {k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items() if not k.endswith("-set")}, flush=True)
    rows_out.append(row)
med = lambda k: float(np.median([r[k] for r in rows_out]))
print("MEDIANS", {k: round(med(k), 5) for k in rows_out[0] if not k.endswith("-set")})
