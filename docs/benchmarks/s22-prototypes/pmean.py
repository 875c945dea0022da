"""Twenty-second session: view-weighted means of each observation's *patch* mean (no voxels).

The stored mean descriptor averages every pixel of every observation's S x S patch; the twenty-first
session's kernels (s21-prototypes/variants.py) weighted the keypoint-centre descriptors by view and
lost to it. Here each observation contributes the mean of its own patch (as the stored mean does) and
the observations are weighted by the angle between the query's and the observation's camera seen
from the landmark: ``pkernelS`` (Gaussian of S degrees; S large: the stored mean) and ``pnearest``
(the nearest observation's patch mean). If a view-weighted patch mean beats the stored mean, a grid
trained on patch-mean targets can. Same arguments as tools/bench_accuracy.py:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s22-prototypes/pmean.py \
        --workdir /tmp/acc19 --reuse --splits fox-extrap --priors noise --no-baseline \
        --variants rendered,mean,nearest-view,pkernel10,pnearest
"""
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tools"))
import bench_accuracy as B
import favormap.localize as L
from favormap import features as feats_mod
from favormap.features import patch_offsets
from favormap.geometry import camera_centers, project
from favormap.io import load_image
from favormap.localize import descriptors as D

PATCH_MEANS = {}
_orig_obs = D.observation_descriptors


def observation_descriptors(map_, sequence, extractor=None):
    """The centre descriptors (as the tool's), and each observation's patch sum stashed for pkernel."""
    names = {f.name: i for i, f in enumerate(sequence.frames)}
    ex = extractor or feats_mod.create(map_.extractor)
    lm, fr, xy = map_.tracks()
    offs = patch_offsets(map_.patch_size)
    centre = np.zeros((len(lm), map_.channels), np.float32)
    psum = np.zeros((len(lm), map_.channels), np.float64)
    pos = np.asarray(map_.positions)
    for f in np.unique(fr):
        frame = sequence.frames[names[map_.frame_names[f]]]
        img, cam = load_image(frame.image_path, sequence.cameras[frame.camera_id], map_.max_side)
        feats = ex.extract(img)
        sel = np.flatnonzero(fr == f)
        centre[sel] = ex.sample(feats, xy[sel])
        uv = project(cam.K, map_.cam_from_world[f], pos[lm[sel]])
        pts = (uv[:, None, :] + offs[None]).reshape(-1, 2)
        psum[sel] = ex.sample(feats, pts).reshape(len(sel), len(offs), -1).mean(1)
    PATCH_MEANS[id(map_)] = psum
    return centre


class PKernel:
    def __init__(self, m, sigma):
        self.name = f"pkernel{sigma:g}" if sigma > 0 else "pnearest"
        lm, fr, _ = m.tracks()
        order = np.lexsort((fr, lm))
        self.lm, self.fr = lm[order], fr[order]
        self.desc = PATCH_MEANS[id(m)][order]
        self.first = np.searchsorted(self.lm, np.arange(len(m) + 1))
        self.centers = camera_centers(m.cam_from_world)
        self.pos = np.asarray(m.positions)
        self.sigma = np.deg2rad(sigma)

    def __call__(self, rows, cam_from_world, timings):
        rows = np.asarray(rows, np.int64)
        n = self.first[rows + 1] - self.first[rows]
        obs = np.repeat(self.first[rows] - np.cumsum(n) + n, n) + np.arange(n.sum())
        group = np.repeat(np.arange(len(rows)), n)
        X = self.pos[rows][group]
        a = self.centers[self.fr[obs]] - X
        b = camera_centers(cam_from_world)[None] - X
        cos = np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        ang = np.arccos(np.clip(cos, -1, 1))
        amin = np.full(len(rows), np.inf)
        np.minimum.at(amin, group, ang)
        if self.sigma > 0:
            w = np.exp(-0.5 * ((ang**2 - amin[group] ** 2) / self.sigma**2))
        else:
            w = (ang <= amin[group]).astype(np.float64)
        out = np.zeros((len(rows), self.desc.shape[1]), np.float64)
        np.add.at(out, group, w[:, None] * self.desc[obs])
        return D.unit_rows(out)


orig = D.make_source


def make_source(name, m, device="cpu", obs=None):
    if name.startswith("pkernel"):
        return PKernel(m, float(name[7:]))
    if name == "pnearest":
        return PKernel(m, 0)
    return orig(name, m, device, obs)


D.observation_descriptors = observation_descriptors
L.make_source = make_source
D.make_source = make_source
for s in (3, 6, 10, 15, 20, 30, 60, 1000):
    B.VARIANTS[f"pkernel{s}"] = (f"pkernel{s}", {})
B.VARIANTS["pnearest"] = ("pnearest", {})
if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
