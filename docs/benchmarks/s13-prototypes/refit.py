# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
"""Offline: refit the final weighted refinement with alternative landmark covariance models."""
import sys
import numpy as np
sys.path.insert(0, "/work/main/tools")
import bench_accuracy as B
from favormap.localize import Localizer, make_source, LocalizeConfig
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.localize.refine import refine_pose, landmark_covariances, estimate_noise
from favormap.mapfile import Map
from favormap.geometry import pose_error
from pathlib import Path
split_name = sys.argv[1]
split = B.orbit_split(Path("/tmp/acc12"), 24, 640, 480) if split_name == "orbit" else B.fox_splits([split_name])[0]

def cov_power(m, rows, sig, p):
    rows = np.asarray(rows)
    c = landmark_covariances(m, rows, sig)
    n = np.maximum(np.asarray(m.track_length[rows], np.float64), 1.0)
    return c * (n ** (1 - 2 * p))[:, None, None]  # sqrt(n) -> n^p in std

for mp in sys.argv[2:]:
    m = Map.open(mp)
    loc = Localizer(m, LocalizeConfig(), descriptor_source=make_source("rendered", m))
    priors = make_priors(split.queries, m.cam_from_world, EvalConfig())
    out = {}
    for fr, prior in zip(split.queries.frames, priors):
        cam0 = split.queries.cameras[fr.camera_id]
        res = loc.localize(fr.image_path, prior, cam0)
        gt = fr.cam_from_world
        img, cam = loc.prepare(fr.image_path, cam0)
        mi = res.matches[res.inlier_mask]
        X, u = m.positions[mi[:, 0]].astype(np.float64), res.keypoints[mi[:, 1]].astype(np.float64)
        sig = loc._landmark_sigma(mi[:, 0])
        e = {"default": pose_error(res.cam_from_world, gt)[0]}
        for name, cov in [("p0.5", landmark_covariances(m, mi[:, 0], sig)), ("p1", cov_power(m, mi[:, 0], sig, 1.0)),
                          ("p0.75", cov_power(m, mi[:, 0], sig, 0.75)), ("p1.5", cov_power(m, mi[:, 0], sig, 1.5))]:
            T, l, s = estimate_noise(res.cam_from_world, X, u, cam.K, cov)
            e[name] = pose_error(T, gt)[0]
        for k, x in e.items():
            out.setdefault(k, []).append(x)
    ref = np.array(out["p0.5"])
    print(mp, {k: round(float(np.median(x)), 5) for k, x in out.items()},
          {k: round(float(np.exp(np.mean(np.log(np.array(x) / ref)))), 3) for k, x in out.items()}, flush=True)
