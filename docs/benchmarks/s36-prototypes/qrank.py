"""Prototype (thirty-sixth session): can the warped track, described in each candidate keypoint's own
SIFT frame, pick the right query keypoint for a landmark better than the map's mean descriptor?
For each visible landmark of a query (true pose), the candidates are the query's detected keypoints
within RADIUS px of its projection; the right one is the nearest within 1.5 px (pairs without one, or
with one candidate only, are left out). Each candidate is scored by its descriptor's cosine to
  mean:  the map's mean descriptor (what favormap stores),
  warpN: the mean over the N observations nearest in angle of the mapping image warped into the query
         by the landmark's local plane (estimated normal) and described at the landmark's projection
         in the candidate's frame (its size, angle, octave).
Prints top-1 accuracy and the median ratio second-best / best score by angle bin.
Run from the repository root: PYTHONPATH=. python docs/benchmarks/s36-prototypes/qrank.py [QSTEP LSTEP RADIUS]"""

import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "s17-prototypes"))
from warp_setup import *  # noqa: F403,E402

qstep, lstep, radius = (int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])) if len(sys.argv) > 3 else (4, 4, 8.0)
gray_train = [cv2.cvtColor(t, cv2.COLOR_RGB2GRAY) for t in train_imgs]  # noqa: F405
T_ = 64
NS = (1, 2, 4, 99)
out = {k: [] for k in ["angle", "ncand", "mean", *[f"warp{n}" for n in NS]]}
t0 = time.time()
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
    tree = cKDTree(qf.keypoints.astype(np.float64))
    c = camera_centers(T)  # noqa: F405
    tiles, tile_pt, entries = [], [], []  # entries: (pair, candidate index, tile index, obs rank)
    pairs = []
    for k, j in enumerate(vis):
        cand = np.array(tree.query_ball_point(uv[k], radius), int)
        if len(cand) < 2:
            continue
        dd = np.linalg.norm(qf.keypoints[cand] - uv[k], axis=1)
        if dd.min() > 1.5:
            continue
        right = cand[np.argmin(dd)]
        s, e = tr.offsets[j], tr.offsets[j + 1]  # noqa: F405
        fr = tr.frame_idx[s:e]  # noqa: F405
        u = c - X[j]  # noqa: F405
        u /= np.linalg.norm(u)
        v = C[fr] - X[j]  # noqa: F405
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        a = np.degrees(np.arccos(np.clip(v @ u, -1, 1)))
        order = np.argsort(a)
        p = len(pairs)
        pairs.append((j, cand, right, a[order[0]]))
        c0 = np.floor(uv[k]) - T_
        Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
        for rank, i in enumerate(order[: max(NS[:-1])] if False else order):
            f = fr[i]
            Hm = homography(Tw[f], T, X[j], n_est[j])  # noqa: F405
            tiles.append(cv2.warpPerspective(gray_train[f], Tr_ @ Hm, (2 * T_, 2 * T_), flags=cv2.INTER_LINEAR))
            tile_pt.append(uv[k] - c0)
            for ci in cand:
                entries.append((p, ci, len(tiles) - 1, rank))
    if not pairs:
        continue
    E = np.array(entries)
    cols = 32
    rows = (len(tiles) + cols - 1) // cols
    mos = np.zeros((rows * 2 * T_, cols * 2 * T_), np.uint8)
    offs = np.zeros((len(tiles), 2), np.float32)
    for i, t in enumerate(tiles):
        r, cc = divmod(i, cols)
        mos[r * 2 * T_ : (r + 1) * 2 * T_, cc * 2 * T_ : (cc + 1) * 2 * T_] = t
        offs[i] = [cc * 2 * T_, r * 2 * T_]

    class S:
        gray = mos

    pts = (np.array(tile_pt, np.float32) + offs)[E[:, 2]]
    d = ex._describe(S, pts, st.size[E[:, 1]], st.angle[E[:, 1]], st.octave[E[:, 1]])  # noqa: F405
    for p, (j, cand, right, ang) in enumerate(pairs):
        qd = qf.descriptors[cand]
        out["angle"].append(ang)
        out["ncand"].append(len(cand))
        sc = {"mean": qd @ mean_desc[j]}  # noqa: F405
        sel = E[:, 0] == p
        for n in NS:
            acc = np.zeros((len(cand), 128))
            m = sel & (E[:, 3] < n)
            ci = np.searchsorted(cand, E[m, 1]) if np.all(np.diff(cand) > 0) else np.array([list(cand).index(x) for x in E[m, 1]])
            np.add.at(acc, ci, d[m])
            acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-12)
            sc[f"warp{n}"] = np.sum(acc * qd, 1)
        ri = list(cand).index(right)
        for key, s_ in sc.items():
            o = np.argsort(-s_)
            best, second = s_[o[0]], s_[o[1]]
            out[key].append((o[0] == ri, second / max(best, 1e-9), s_[ri]))
    print(kind, len(pairs), len(tiles), len(E), f"{time.time() - t0:.0f}s", flush=True)
A = np.array(out["angle"])
bins = [(0, 10), (10, 20), (20, 40), (40, 180), (0, 180)]
print("pairs", len(A), "median candidates", np.median(out["ncand"]), "radius", radius)
print("top-1 right / median(second/best) / mean score of the right one, bins", bins)
for key in ["mean", *[f"warp{n}" for n in NS]]:
    v = np.array(out[key], float)
    cells = []
    for lo, hi in bins:
        b = (A >= lo) & (A < hi)
        cells.append(f"{v[b, 0].mean():.3f}/{np.median(v[b, 1]):.3f}/{v[b, 2].mean():.3f} ({b.sum()})" if b.any() else "-")
    print(f"{key:7s}", "  ".join(cells))
