"""Map geometry vs localizer: favormap landmarks vs baseline points, same query keypoints (OpenCV
SIFT, favormap's extractor), correspondences by GT projection within R px (nearest keypoint),
pycolmap LO-RANSAC + refine: each query's translation error / inliers for favormap's landmarks, the
baseline's 3,000 longest-track points and all its points. Usage: PYTHONPATH=. python gt_correspondences.py DIR [R]."""

import sys

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from favormap.features import create
from favormap.geometry import from_rigid3d, pose_error, project
from favormap.io import read_sequence
from favormap.io.images import load_image
from favormap.mapfile.reader import Map

d = sys.argv[1]
R = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
q = read_sequence(f"{d}/orbit_queries")
mp = read_sequence(f"{d}/orbit_map")
m = Map(f"{d}/orbit.h5")
P_f = m.positions.astype(np.float64)
rec = pycolmap.Reconstruction(f"{d}/orbit_baseline/sparse")
pts = np.array([p.xyz for p in rec.points3D.values()])
tl = np.array([p.track.length() for p in rec.points3D.values()])
P_b = pts[np.argsort(-tl)[:3000]]
ex = create("sift", max_keypoints=4096)
cent_map = np.array([np.linalg.inv(f.cam_from_world)[:3, 3] for f in mp.frames])
res = {"favormap": [], "baseline3000": [], "baseline-all": []}
angs = []
for fr in q.frames:
    img, cam = load_image(fr.image_path, q.cameras[fr.camera_id], 640)
    kp = ex.extract(img).keypoints.astype(np.float64)
    tree = cKDTree(kp)
    T = fr.cam_from_world
    for name, P in (("favormap", P_f), ("baseline3000", P_b), ("baseline-all", pts)):
        uv, z = project(cam.K, T, P, with_depth=True)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
        dist, nn = tree.query(uv[ok])
        sel = dist <= R
        X = P[ok][sel]
        x = kp[nn[sel]]
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = 4.0
        ans = pycolmap.estimate_and_refine_absolute_pose(x, X, cam.to_pycolmap(), est)
        e = pose_error(from_rigid3d(ans["cam_from_world"]), T)[0] if ans else np.nan
        res[name].append((e, int(sel.sum()), int(ans["num_inliers"]) if ans else 0))
    print(fr.image_path.name, [f"{res[k][-1][0]:.5f}/{res[k][-1][2]}" for k in res], flush=True)
