"""Prototype: does warping the nearest training view by the landmark's local plane predict the
query's SIFT descriptor better than the nearest view / mean? (bench_novel_view's orbit scene)"""
import time

import cv2
import numpy as np

from warp_setup import *  # noqa: F403 (scene, landmarks, rays, normals, homography, query_pairs)

res = {k: [] for k in ["angle", "nearest", "mean", "warp_true", "warp_est", "warp_true_mean", "warp_est_mean"]}
t0 = time.time()
for kind, T, vis, uv, truth, near_f, near_o, ang in query_pairs(2, 4):
    # rays obs index == track obs index (rays sorted by landmark, same order as tracks)
    res["angle"].append(ang); res["nearest"].append(np.sum(ct[near_o] * truth, 1))
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))
    for name, normals in [("warp_true", n_true), ("warp_est", n_est)]:
        pred = np.zeros_like(truth); predm = np.zeros_like(truth)
        for k, j in enumerate(vis):
            acc = np.zeros(128)
            for oi in range(tr.offsets[j], tr.offsets[j + 1]):
                f = tr.frame_idx[oi]
                Hm = homography(Tw[f], T, X[j], normals[j])
                c0 = np.floor(uv[k]) - 64
                Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
                patch = cv2.warpPerspective(train_imgs[f], Tr_ @ Hm, (128, 128), flags=cv2.INTER_LINEAR)
                dsc = ex.sample(ex.extract(patch), (uv[k] - c0)[None])[0]
                acc += dsc
                if oi == near_o[k]:
                    pred[k] = dsc
            predm[k] = acc / np.linalg.norm(acc)
        res[name].append(np.sum(pred * truth, 1))
        res[name + "_mean"].append(np.sum(predm * truth, 1))
    print(kind, len(vis), f"{time.time()-t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS)
for k in ["nearest", "mean", "warp_true", "warp_est", "warp_true_mean", "warp_est_mean"]:
    print(f"{k:12s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))
print("pairs", len(A), [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])
