"""How far interpolated patch descriptors lie from described ones (twenty-fifth session, issue 14; the
twenty-fourth session's interp_cos.py with more grids, and grids whose centre pixel is described too).

Fox frames 0, 10 and 25 at 640 px, 300 SIFT keypoints each moved by up to 0.7 px (a landmark's
projection lies near, not on, its keypoint), their 7 x 7 patches described at every pixel (the
truth) and on coarser grids whose other pixels are bilinear blends of the described ones.
Prints, per grid: mean and 5th-percentile cosine of every patch pixel to the truth, the centre
pixel's, the cosine of the patch's mean descriptor to the true patch mean, and the time of the
described points on one thread.

    PYTHONPATH=. python docs/benchmarks/s25-prototypes/interp_cos2.py [FOX_DIR]
"""

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from favormap.features.sift import SIFTExtractor

cv2.setNumThreads(1)
fox = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/fox")
frames = json.loads((fox / "transforms.json").read_text())["frames"]
ex = SIFTExtractor(max_keypoints=2048)
o7 = np.stack(np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)), -1).reshape(-1, 2).astype(np.float32)


def interp_mat(g):
    W = np.zeros((7, len(g)))
    for i, x in enumerate(range(-3, 4)):
        j = min(max(np.searchsorted(g, x, side="right") - 1, 0), len(g) - 2)
        t = (x - g[j]) / (g[j + 1] - g[j])
        W[i, j], W[i, j + 1] = 1 - t, t
    return W


# name: (separable grid, whether the centre pixel is described as well)
grids = {
    "(-3,-1,0,1,3), the 24th session's": (np.array([-3, -1, 0, 1, 3.0]), False),
    "(-3,-2,0,2,3)": (np.array([-3, -2, 0, 2, 3.0]), False),
    "(-3,-1,1,3)": (np.array([-3, -1, 1, 3.0]), False),
    "(-3,-1,1,3) + centre": (np.array([-3, -1, 1, 3.0]), True),
    "(-3,0,3)": (np.array([-3, 0, 3.0]), False),
    "(-3,-1.5,0,1.5,3)": (np.array([-3, -1.5, 0, 1.5, 3.0]), False),
    "(-3,-2,2,3) + centre": (np.array([-3, -2, 2, 3.0]), True),
}
res = {}
for fi in [0, 10, 25]:
    img = cv2.imread(str(fox / frames[fi]["file_path"]))[:, :, ::-1]
    s = 640 / max(img.shape[:2])
    img = np.ascontiguousarray(cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA))
    f = ex.extract(img)
    rng = np.random.default_rng(fi)
    sel = rng.choice(len(f.keypoints), 300, replace=False)
    kp = f.keypoints[sel] + rng.uniform(-0.7, 0.7, (300, 2)).astype(np.float32)
    truth = ex.sample(f, (kp[:, None] + o7[None]).reshape(-1, 2)).reshape(300, 49, 128)
    for name, (g, centre) in grids.items():
        W = interp_mat(g)
        og = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2).astype(np.float32)
        if centre:
            og = np.concatenate([og, np.zeros((1, 2), np.float32)])
        t = time.perf_counter()
        d = ex.sample(f, (kp[:, None] + og[None]).reshape(-1, 2)).reshape(300, len(og), 128)
        dt = time.perf_counter() - t
        sep = d[:, : len(g) ** 2].reshape(300, len(g), len(g), 128)
        full = np.einsum("yj,xi,njic->nyxc", W, W, sep).reshape(300, 49, 128)
        full /= np.linalg.norm(full, axis=-1, keepdims=True)
        if centre:
            full[:, 24] = d[:, -1]
        cos = (full * truth).sum(-1)
        mt = truth.mean(1)
        mt /= np.linalg.norm(mt, axis=-1, keepdims=True)
        mi = full.mean(1)
        mi /= np.linalg.norm(mi, axis=-1, keepdims=True)
        res.setdefault(name, []).append(
            (cos.mean(), np.percentile(cos, 5), cos[:, 24].mean(), (mt * mi).sum(-1).mean(), dt)
        )
for k, v in res.items():
    print(f"{k:36s} cos mean %.4f p5 %.3f centre %.4f patch mean %.5f described in %.2f s" % tuple(np.mean(v, 0)))
