"""Geometric re-association after localization: from the localizer's pose, each landmark visible from it is paired
with the detected keypoint nearest its projection (mutually, within R px), refined (estimate_noise), repeated."""
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

path = Path(sys.argv[1]); align = "align" in sys.argv
split = B.fox_splits(["fox-extrap"])[0]
m = Map.open(path)
priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
locs = {s: Localizer(m, dc.replace(B.localizer_config({"align": align}), descriptors=s), descriptor_source=make_source(s, m, "cpu", None)) for s in ("rendered", "mean")}
out = []
def assoc(loc, T, cam, kp, R):
    vis = visible_rows(loc.index, cam, T, m.view_dir, m.view_angle, m.depth_range, loc.config.view_limits)
    uv = project(cam.K, T, loc.positions[vis])
    d1, j1 = cKDTree(kp).query(uv)
    d2, j2 = cKDTree(uv).query(kp)
    ok = (d1 < R) & (j2[j1] == np.arange(len(uv)))
    return vis[ok], kp[j1[ok]]
def refine(loc, T, K, lm, kp):
    cov = landmark_covariances(m, lm, loc._landmark_sigma(lm))
    return estimate_noise(T, loc.positions[lm], kp, K, cov, loc.config.keypoint_sigma_px)[0]
for i, fr in enumerate(split.queries.frames):
    cam0 = split.queries.cameras[fr.camera_id]; gt = fr.cam_from_world
    row = {}
    for s, loc in locs.items():
        res = loc.localize(fr.image_path, priors[i], cam0)
        row[s] = pose_error(res.cam_from_world, gt)[0] if res.success else np.inf
        img, cam = loc.prepare(fr.image_path, cam0)
        kp = np.asarray(loc.extractor.extract(img).keypoints, np.float64)
        for R in (1.5, 3.0):
            T = res.cam_from_world
            for _ in range(4):
                lm, k = assoc(loc, T, cam, kp, R)
                if len(lm) < 12: break
                T = refine(loc, T, cam.K, lm, k)
            row[f"{s} icp{R:g}"] = pose_error(T, gt)[0]
            # coarse-to-fine: 3 px then 1.5 px
        T = res.cam_from_world
        for R in (3.0, 3.0, 2.0, 1.5, 1.5):
            lm, k = assoc(loc, T, cam, kp, R)
            if len(lm) < 12: break
            T = refine(loc, T, cam.K, lm, k)
        row[f"{s} icp-c2f"] = pose_error(T, gt)[0]
    print(i, {k: round(v, 4) for k, v in row.items()}, flush=True)
    out.append(row)
print("MEDIANS", {k: round(float(np.median([r[k] for r in out])), 5) for k in out[0]})
g = lambda a, b: float(np.exp(np.mean(np.log([r[a] / r[b] for r in out]))))
print("PAIRED", {k: round(g(k, k.split()[0]), 3) for k in out[0] if " " in k}, "mean/rendered", round(g("mean", "rendered"), 3))
