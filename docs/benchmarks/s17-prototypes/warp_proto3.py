"""Prototype: does warping the nearest training view by the landmark's local plane predict the
query's SIFT descriptor better than the nearest view / mean? (bench_novel_view's orbit scene)"""
import time

import cv2
import numpy as np

from warp_setup import *  # noqa: F403 (scene, landmarks, rays, normals, homography, query_pairs)

res = {k: [] for k in ["angle", "nearest", "mean", "warp_true", "warp_est", "pred+1", "pred-1"]}
t0 = time.time()
for kind, T, vis, uv, truth, near_f, near_o, ang in query_pairs(2, 4):
    # rays obs index == track obs index (rays sorted by landmark, same order as tracks)
    res["angle"].append(ang); res["nearest"].append(np.sum(ct[near_o] * truth, 1))
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))
    for sign in (1, -1):
        name = f"pred{sign:+d}"
        tiles, sizes_, angs, tile_lm = [], [], [], []
        for k, j in enumerate(vis):
            for oi in range(tr.offsets[j], tr.offsets[j + 1]):
                f = tr.frame_idx[oi]; st = ff.features[f].dense; kp = tr.keypoint_idx[oi]
                Hm = homography(Tw[f], T, X[j], n_est[j])
                c0 = np.floor(uv[k]) - 32
                Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
                tiles.append(cv2.warpPerspective(st.gray, Tr_ @ Hm, (64, 64), flags=cv2.INTER_LINEAR))
                p = tr.xy[oi]; w = Hm[2] @ [p[0], p[1], 1]; xq = (Hm[:2] @ [p[0], p[1], 1]) / w
                A = (Hm[:2, :2] - np.outer(xq, Hm[2, :2])) / w
                th = np.radians(st.angle[kp]); u = A @ [np.cos(th), sign * np.sin(th)]
                angs.append(np.degrees(np.arctan2(sign * u[1], u[0])) % 360)
                sizes_.append(st.size[kp] * np.sqrt(abs(np.linalg.det(A))))
                tile_lm.append((k, uv[k] - c0))
        n = len(tiles); cols = 64; rows = (n + cols - 1) // cols
        mos = np.zeros((rows * 64, cols * 64), np.uint8)
        pts = np.zeros((n, 2), np.float32)
        for i, t in enumerate(tiles):
            r, c = divmod(i, cols); mos[r*64:(r+1)*64, c*64:(c+1)*64] = t
            pts[i] = tile_lm[i][1] + [c * 64, r * 64]
        class S: pass
        S.gray = mos
        sz = np.array(sizes_, np.float32)
        from favormap.features.sift import octave_of_size
        dsc = ex._describe(S, pts, sz, np.array(angs, np.float32), octave_of_size(sz))
        acc = np.zeros_like(truth)
        np.add.at(acc, [t[0] for t in tile_lm], dsc)
        acc /= np.linalg.norm(acc, axis=1, keepdims=True)
        res[name].append(np.sum(acc * truth, 1))
    print(kind, len(vis), f"{time.time()-t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS)
for k in ["nearest", "mean", "pred+1", "pred-1"]:
    print(f"{k:12s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))
print("pairs", len(A), [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])
