"""Prototype: does warping the nearest training view by the landmark's local plane predict the
query's SIFT descriptor better than the nearest view / mean? (bench_novel_view's orbit scene)"""
import time

import cv2
import numpy as np

from favormap.features.sift import octave_of_size
from warp_setup import *  # noqa: F403 (scene, landmarks, rays, normals, homography, query_pairs)

res = {k: [] for k in ["angle", "nearest", "mean", "warp_true", "warp_est", "oneframe"]}
t0 = time.time()
for kind, T, vis, uv, truth, near_f, near_o, ang in query_pairs(2, 4):
    # rays obs index == track obs index (rays sorted by landmark, same order as tracks)
    res["angle"].append(ang); res["nearest"].append(np.sum(ct[near_o] * truth, 1))
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))
    tiles, sizes_, angs, octs, tile_lm = [], [], [], [], []
    for k, j in enumerate(vis):
        c0 = np.floor(uv[k]) - 64
        Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
        # the query's keypoint frame, predicted by detecting on the nearest view warped into the query
        f = near_f[k]
        patch = cv2.warpPerspective(train_imgs[f], Tr_ @ homography(Tw[f], T, X[j], n_est[j]), (128, 128), flags=cv2.INTER_LINEAR)
        feat = ex.extract(patch); p = (uv[k] - c0).astype(np.float32)
        size, angle, octv = ex.size, 0.0, int(octave_of_size(ex.size))
        if len(feat.dense.xy):
            dd = np.linalg.norm(feat.dense.xy - p, axis=1); m = np.argmin(dd)
            if dd[m] <= ex.support_px:
                size, angle, octv = feat.dense.size[m], feat.dense.angle[m], feat.dense.octave[m]
        for oi in range(tr.offsets[j], tr.offsets[j + 1]):
            f = tr.frame_idx[oi]
            Hm = homography(Tw[f], T, X[j], n_est[j])
            tiles.append(cv2.cvtColor(cv2.warpPerspective(train_imgs[f], Tr_ @ Hm, (128, 128), flags=cv2.INTER_LINEAR), cv2.COLOR_RGB2GRAY))
            sizes_.append(size); angs.append(angle); octs.append(octv); tile_lm.append((k, uv[k] - c0))
    n = len(tiles); cols = 32; rows = (n + cols - 1) // cols
    mos = np.zeros((rows * 128, cols * 128), np.uint8)
    pts = np.zeros((n, 2), np.float32)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols); mos[r*128:(r+1)*128, c*128:(c+1)*128] = t
        pts[i] = tile_lm[i][1] + [c * 128, r * 128]
    class S: pass
    S.gray = mos
    dsc = ex._describe(S, pts, np.array(sizes_, np.float32), np.array(angs, np.float32), np.array(octs, np.int64))
    acc = np.zeros_like(truth)
    np.add.at(acc, [t[0] for t in tile_lm], dsc)
    acc /= np.linalg.norm(acc, axis=1, keepdims=True)
    res["oneframe"].append(np.sum(acc * truth, 1))
    print(kind, len(vis), f"{time.time()-t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS)
for k in ["nearest", "mean", "oneframe"]:
    print(f"{k:12s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))
print("pairs", len(A), [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])
