"""Twenty-first session: tools/bench_accuracy.py with prototype descriptor sources, localizer variants
and extractors (none of them in the package). Run from the repository root, same arguments as the tool:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s21-prototypes/variants.py \
        --workdir /tmp/acc19 --reuse --splits fox-extrap --priors noise --no-baseline \
        --variants rendered,mean,kernel10,blend1 --build-variant "w10e1:match_window=10,max_epipolar_px=1.0"

- ``kernelS``: the view-kernel-weighted mean of a landmark's observed (keypoint-centre) descriptors,
  weight exp(-a^2 / 2 S^2), a the angle at the landmark between the query's and the observation's
  camera centres (no voxels; S in degrees; list nearest-view among the variants too, so that the
  tool computes the observation descriptors);
- ``blendW``: unit(rendered + W * mean);
- ``rendered match-T`` / ``mean match-T``: descriptor and guided matching at cosine T instead of 0.7;
- ``--extractor siftdisk`` / ``siftdisk2``: see siftdisk.py."""
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tools"))
sys.path.insert(0, str(HERE))
import bench_accuracy as B
import siftdisk  # noqa: F401 - registers the prototype extractors
import favormap.localize as L
from favormap.localize import descriptors as D
from favormap.geometry import camera_centers


class Kernel:
    def __init__(self, m, obs_desc, sigma):
        self.name = f"kernel{sigma:g}"
        lm, fr, _ = m.tracks()
        order = np.lexsort((fr, lm))
        self.lm, self.fr = lm[order], fr[order]
        self.desc = D.unit_rows(obs_desc[order])
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
        # weights relative to the group's nearest view (avoid underflow)
        amin = np.full(len(rows), np.inf)
        np.minimum.at(amin, group, ang)
        w = np.exp(-0.5 * ((ang**2 - amin[group] ** 2) / self.sigma**2))
        out = np.zeros((len(rows), self.desc.shape[1]), np.float64)
        np.add.at(out, group, w[:, None] * self.desc[obs])
        return D.unit_rows(out)


orig = D.make_source


class Blend:
    def __init__(self, m, w):
        self.name = f"blend{w:g}"
        self.r, self.m, self.w = orig("rendered", m), orig("mean", m), w

    def __call__(self, rows, cam_from_world, timings):
        return D.unit_rows(self.r(rows, cam_from_world, timings) + self.w * self.m(rows, cam_from_world, timings))


def make_source(name, m, device="cpu", obs=None):
    if name.startswith("blend"):
        return Blend(m, float(name[5:]))
    if name.startswith("kernel"):
        return Kernel(m, obs, float(name[6:]))
    return orig(name, m, device, obs)


L.make_source = make_source
D.make_source = make_source
for s in (3, 6, 10, 15, 20, 30, 60):
    B.VARIANTS[f"kernel{s}"] = (f"kernel{s}", {})
for t in (0.4, 0.5, 0.6):
    for src in ("rendered", "mean"):
        B.VARIANTS[f"{src} match-{t:g}"] = (src, {"match_threshold": t, "guided_match_threshold": t})
B.VARIANTS["rendered match-0.5 8192"] = ("rendered", {"match_threshold": 0.5, "guided_match_threshold": 0.5, "max_keypoints": 8192})
for w in (0.5, 1, 2):
    B.VARIANTS[f"blend{w:g}"] = (f"blend{w:g}", {})
if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
