"""Twenty-eighth session: the final weighted refinement with each correspondence's noise scaled by its
query keypoint's SIFT scale (as ORB-SLAM scales its reprojection errors by the keypoint's octave).
tools/bench_accuracy.py with the variants ``rendered kps1`` (sigma proportional to the keypoint size
over the inliers' median size) and ``rendered kps05`` (to its square root); run from the repository root,
the same arguments as the tool:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s28-prototypes/kpscale.py \
        --workdir /tmp/acc28 --reuse --splits fox-extrap,fox-holdout,orbit --priors noise --no-baseline \
        --variants "rendered,rendered kps1,rendered kps05"
"""

import sys
import threading
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tools"))
import bench_accuracy as B  # noqa: E402

import favormap.localize as L  # noqa: E402
import favormap.localize.localizer as LL  # noqa: E402
from favormap.localize import descriptors as D  # noqa: E402

_state = threading.local()
orig_source, orig_weighted, orig_refine = D.make_source, LL.Localizer._weighted, LL.refine_pose


def make_source(name, m, device="cpu", obs=None):
    return orig_source(name.split("-kps")[0], m, device, obs)


def weighted(self, q, it, last, t):
    name = self.config.descriptors
    _state.w = None
    if "-kps" in name:
        power = {"1": 1.0, "05": 0.5}[name.split("-kps")[1]]
        inl = last["matches"][last["inliers"]]
        size = np.asarray(q.feats.dense.size, np.float64)[inl[:, 1]]
        _state.w = (size / np.median(size)) ** (2 * power)  # variance factor
    try:
        return orig_weighted(self, q, it, last, t)
    finally:
        _state.w = None


def refine_pose(T, X, kp, K, cov=None, ksig=0.5, *args, **kw):
    w = getattr(_state, "w", None)
    if w is not None and len(w) == len(X):
        f = kw.get("variance_factor")
        kw["variance_factor"] = w if f is None else np.asarray(f) * w
    return orig_refine(T, X, kp, K, cov, ksig, *args, **kw)


L.make_source = D.make_source = make_source
LL.Localizer._weighted = weighted
LL.refine_pose = refine_pose
B.VARIANTS["rendered kps1"] = ("rendered-kps1", {})
B.VARIANTS["rendered kps05"] = ("rendered-kps05", {})
B.VARIANTS["mean kps1"] = ("mean-kps1", {})

if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
