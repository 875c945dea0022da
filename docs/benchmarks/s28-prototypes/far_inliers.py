"""The orbit's far queries (> 40 deg from every mapping view) localized against several maps from the
ground-truth pose as prior: each query's error, its inliers' residuals at the ground truth (the
landmark projected with the true pose against its matched keypoint) and the track lengths of the
inliers, and the error of pycolmap's estimate from those inliers alone. Usage, from the repository root, with a tools/bench_accuracy.py --workdir DIR:
PYTHONPATH=. python docs/benchmarks/s28-prototypes/far_inliers.py DIR RUN.json.gz orbit.h5 orbit-kp4k3.h5 ..."""

import gzip
import json
import sys

import numpy as np
import pycolmap

from favormap.geometry import from_rigid3d, pose_error, project
from favormap.io import read_sequence
from favormap.localize import Localizer

d, run, maps = sys.argv[1], sys.argv[2], sys.argv[3:]
rows = json.loads(gzip.decompress(open(run, "rb").read()))
row = next(r for r in rows if r["split"] == "orbit" and r["method"] == "rendered" and r["prior"] == "noise")
far = {q["name"]: q["angle_deg"] for q in row["per_query"] if q["angle_deg"] > 40}
seq = read_sequence(f"{d}/orbit_queries")
for name in maps:
    loc = Localizer(f"{d}/{name}")
    errs, res_all, tl_all = [], [], []
    for fr in seq.frames:
        if fr.name not in far:
            continue
        T = fr.cam_from_world
        r = loc.localize(fr.image_path, T, seq.cameras[fr.camera_id])
        e = pose_error(r.cam_from_world, T)[0]
        inl = r.matches[r.inlier_mask]
        uv = project(r.camera.K, T, loc.positions[inl[:, 0]])
        res = np.linalg.norm(uv - r.keypoints[inl[:, 1]], axis=1)
        tl = np.asarray(loc.map.track_length)[inl[:, 0]]
        # the same inliers given to pycolmap alone (LO-RANSAC at 4 px, then its refinement)
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = 4.0
        ans = pycolmap.estimate_and_refine_absolute_pose(
            r.keypoints[inl[:, 1]].astype(np.float64),
            loc.positions[inl[:, 0]].astype(np.float64),
            r.camera.to_pycolmap(),
            est,
        )
        e_lsq = pose_error(from_rigid3d(ans["cam_from_world"]), T)[0] if ans else float("nan")
        errs.append(e)
        res_all.append(res)
        tl_all.append(tl)
        print(
            f"{name} {fr.name} {far[fr.name]:.0f} deg err {e:.5f} inliers {len(res)} GT residual median "
            f"{np.median(res):.2f} px, > 2 px {np.mean(res > 2):.2f}, > 3 px {np.mean(res > 3):.2f}; "
            f"track length median {np.median(tl):.0f}; pycolmap on these inliers: err {e_lsq:.5f}",
            flush=True,
        )
    R, L = np.concatenate(res_all), np.concatenate(tl_all)
    print(
        f"== {name}: median error {np.median(errs):.5f}; inliers' GT residual median {np.median(R):.2f} px, "
        f"> 2 px {np.mean(R > 2):.2f}; by track length 3-4 / 5-7 / 8-11 / >= 12: "
        + " / ".join(
            f"{(s := (L >= a) & (L <= b)).sum()} at {np.median(R[s]) if s.any() else float('nan'):.2f} px"
            for a, b in ((3, 4), (5, 7), (8, 11), (12, 10**6))
        ),
        flush=True,
    )
