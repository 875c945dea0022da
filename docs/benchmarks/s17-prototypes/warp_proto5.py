"""Prototype: does warping the nearest training view by the landmark's local plane predict the
query's SIFT descriptor better than the nearest view / mean? (bench_novel_view's orbit scene)"""
import time

import cv2
import numpy as np

from warp_setup import *  # noqa: F403 (scene, landmarks, rays, normals, homography, query_pairs)

res = {k: [] for k in ["angle", "nearest", "mean", "warp_true", "warp_est", "mosaic"]}
TIMES = []
exm = features.create("sift", max_keypoints=10**7)
t0 = time.time()
for kind, T, vis, uv, truth, near_f, near_o, ang in query_pairs(2, 4):
    # rays obs index == track obs index (rays sorted by landmark, same order as tracks)
    res["angle"].append(ang); res["nearest"].append(np.sum(ct[near_o] * truth, 1))
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))
    t1 = time.perf_counter()
    tiles, tile_lm = [], []
    for k, j in enumerate(vis):
        c0 = np.floor(uv[k]) - 64
        Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
        for oi in range(tr.offsets[j], tr.offsets[j + 1]):
            f = tr.frame_idx[oi]
            Hm = homography(Tw[f], T, X[j], n_est[j])
            tiles.append(cv2.warpPerspective(train_imgs[f], Tr_ @ Hm, (128, 128), flags=cv2.INTER_LINEAR))
            tile_lm.append((k, uv[k] - c0))
    n = len(tiles); cols = 32; rows = (n + cols - 1) // cols
    mos = np.zeros((rows * 128, cols * 128, 3), np.uint8)
    pts = np.zeros((n, 2), np.float32)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols); mos[r*128:(r+1)*128, c*128:(c+1)*128] = t
        pts[i] = tile_lm[i][1] + [c * 128, r * 128]
    t2 = time.perf_counter()
    dsc = exm.sample(exm.extract(mos), pts)
    t3 = time.perf_counter()
    TIMES.append((n, t2 - t1, t3 - t2))
    acc = np.zeros_like(truth)
    np.add.at(acc, [t[0] for t in tile_lm], dsc)
    acc /= np.linalg.norm(acc, axis=1, keepdims=True)
    res["mosaic"].append(np.sum(acc * truth, 1))
    print(kind, len(vis), f"{time.time()-t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS)
for k in ["nearest", "mean", "mosaic"]:
    print(f"{k:12s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))
print("pairs", len(A), [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])

n = sum(t[0] for t in TIMES); print(f"tiles {n}: warp+mosaic {sum(t[1] for t in TIMES):.1f}s, detect+describe {sum(t[2] for t in TIMES):.1f}s, {1000*sum(t[1]+t[2] for t in TIMES)/n:.2f} ms per tile")
