"""Prototype (thirty-sixth session): the seventeenth session's warped-track mean, but every warped
observation described in the query keypoint's own SIFT frame (size, angle, octave of the query's
detection nearest the landmark's projection, as the truth is described) instead of a frame detected
on each warped tile. A localizer knows each candidate keypoint's frame, so this needs no detection
on the warped tiles: one descriptor per (pair, observation). Controls: the same frame on the
observations translated only (no warp), and the nearest observation alone.
Run from the repository root: PYTHONPATH=. python docs/benchmarks/s36-prototypes/qframe.py [QSTEP LSTEP]"""

import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "s17-prototypes"))
from warp_setup import *  # noqa: F403,E402

from favormap.features.sift import octave_of_size  # noqa: E402

qstep, lstep = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (2, 4)
gray_train = [cv2.cvtColor(t, cv2.COLOR_RGB2GRAY) for t in train_imgs]  # noqa: F405
obs_xy = tr.xy if hasattr(tr, "xy") else None  # noqa: F405
keys = ["nearest", "mean", "warp_qframe_mean", "warp_qframe_nearest", "shift_qframe_mean", "warp_qframe_mean_w"]
res = {k: [] for k in ["angle", *keys]}
t0 = time.time()
T_ = 64  # tile half-size
for kind, T in queries[::qstep]:  # noqa: F405
    img, depth = render(scene, cam, T)  # noqa: F405
    vis = np.flatnonzero(project_inside(X, cam, T, margin_px=8))  # noqa: F405
    Xc = X[vis] @ T[:3, :3].T + T[:3, 3]  # noqa: F405
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]  # noqa: F405
    ui = np.clip(uv.astype(int), 0, [W - 1, H - 1])  # noqa: F405
    ok = np.abs(depth[ui[:, 1], ui[:, 0]] - Xc[:, 2]) < 0.02 * Xc[:, 2] + 0.005
    vis, uv = vis[ok][::lstep], uv[ok][::lstep]
    qf = ex.extract(img)  # noqa: F405
    st = qf.dense
    # the truth's frame (SIFTExtractor.sample's rule)
    size = np.full(len(uv), ex.size, np.float32)  # noqa: F405
    angle = np.zeros(len(uv), np.float32)
    octv = np.full(len(uv), int(octave_of_size(ex.size)), np.int64)  # noqa: F405
    from scipy.spatial import cKDTree as _T

    dist, nn = _T(st.xy.astype(np.float64)).query(uv, k=1)
    near = dist <= ex.support_px  # noqa: F405
    size[near], angle[near], octv[near] = st.size[nn[near]], st.angle[nn[near]], st.octave[nn[near]]
    truth = ex._describe(st, uv.astype(np.float32), size, angle, octv)  # noqa: F405
    c = camera_centers(T)  # noqa: F405
    tiles_w, tiles_s, pts_s, fr_idx, pair_of, wts, is_near = [], [], [], [], [], [], []
    ang = np.zeros(len(vis))
    near_o = np.zeros(len(vis), int)
    for k, j in enumerate(vis):
        s, e = tr.offsets[j], tr.offsets[j + 1]  # noqa: F405
        fr = tr.frame_idx[s:e]  # noqa: F405
        u = c - X[j]  # noqa: F405
        u /= np.linalg.norm(u)
        v = C[fr] - X[j]  # noqa: F405
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        a = np.degrees(np.arccos(np.clip(v @ u, -1, 1)))
        m = int(np.argmin(a))
        ang[k], near_o[k] = a[m], s + m
        c0 = np.floor(uv[k]) - T_
        Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
        for i, f in enumerate(fr):
            Hm = homography(Tw[f], T, X[j], n_est[j])  # noqa: F405
            tiles_w.append(cv2.warpPerspective(gray_train[f], Tr_ @ Hm, (2 * T_, 2 * T_), flags=cv2.INTER_LINEAR))
            # translation only: the observation's projection of the landmark at the tile's centre offset
            Xr = Tw[f][:3, :3] @ X[j] + Tw[f][:3, 3]  # noqa: F405
            ur = Xr[:2] / Xr[2] * [K[0, 0], K[1, 1]] + K[:2, 2]  # noqa: F405
            d0 = np.floor(ur) - T_
            tiles_s.append(cv2.warpAffine(gray_train[f], np.array([[1, 0, -d0[0]], [0, 1, -d0[1]]]), (2 * T_, 2 * T_)))
            pts_s.append(ur - d0)
            pair_of.append(k)
            wts.append(np.exp(-0.5 * (a[i] / 15.0) ** 2))
            is_near.append(i == m)
    pair_of = np.array(pair_of)
    n = len(pair_of)
    pts_w = (uv[pair_of] - (np.floor(uv[pair_of]) - T_)).astype(np.float32)

    def describe(tiles, pts):
        cols = 32
        rows = (n + cols - 1) // cols
        mos = np.zeros((rows * 2 * T_, cols * 2 * T_), np.uint8)
        p = np.zeros((n, 2), np.float32)
        for i, t in enumerate(tiles):
            r, cc = divmod(i, cols)
            mos[r * 2 * T_ : (r + 1) * 2 * T_, cc * 2 * T_ : (cc + 1) * 2 * T_] = t
            p[i] = pts[i] + [cc * 2 * T_, r * 2 * T_]

        class S:
            gray = mos

        return ex._describe(S, p, size[pair_of], angle[pair_of], octv[pair_of])  # noqa: F405

    def avg(d, w=None):
        acc = np.zeros_like(truth)
        np.add.at(acc, pair_of, d * (1.0 if w is None else np.asarray(w)[:, None]))
        return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-12)

    dw = describe(tiles_w, pts_w)
    ds = describe(tiles_s, np.array(pts_s, np.float32))
    res["angle"].append(ang)
    res["nearest"].append(np.sum(ct[near_o] * truth, 1))  # noqa: F405
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))  # noqa: F405
    res["warp_qframe_mean"].append(np.sum(avg(dw) * truth, 1))
    res["warp_qframe_mean_w"].append(np.sum(avg(dw, wts) * truth, 1))
    sel = np.array(is_near)
    dn = np.zeros_like(truth)
    dn[pair_of[sel]] = dw[sel]
    res["warp_qframe_nearest"].append(np.sum(dn * truth, 1))
    res["shift_qframe_mean"].append(np.sum(avg(ds) * truth, 1))
    print(kind, len(vis), n, f"{time.time() - t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS, "+ all")  # noqa: F405
for k in keys:
    print(f"{k:22s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))  # noqa: F405
print("pairs", len(A), [int(((A >= lo) & (A < hi)).sum()) for lo, hi in bnv.BINS])  # noqa: F405
