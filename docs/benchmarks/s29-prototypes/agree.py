"""Twenty-ninth session: `--align` kept only where two reference views agree. Each inlier is aligned
to its landmark's nearest-direction mapping view and to the second nearest; the aligned keypoint (the
mean of the two) replaces the detected one only where both converged within ``AGREE_PX`` of each other.
tools/bench_accuracy.py variants ``rendered agree`` (0.25 px) and ``rendered agree-0.5`` (run from the
repository root):

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s29-prototypes/agree.py \\
        --workdir /tmp/acc29f --reuse --splits fox-extrap,fox-holdout,orbit --priors noise --no-baseline \\
        --variants "rendered,rendered align,rendered agree,rendered agree-0.5"
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B  # noqa: E402

import favormap.localize.localizer as LL  # noqa: E402
from favormap.localize.align import PlaneAligner  # noqa: E402

_rank = [0]
orig_refs, orig_align, orig_aligned = PlaneAligner.reference_frames, PlaneAligner.align, LL.Localizer._aligned


def reference_frames(self, positions, rows, center):
    """The mapping frame of rank _rank[0] by direction (0: the nearest), the nearest where fewer."""
    if _rank[0] == 0:
        return orig_refs(self, positions, rows, center)
    ix = self.index
    s, e = ix.first[rows], ix.first[rows + 1]
    out = np.full(len(rows), -1, np.int64)
    for i, j in enumerate(rows):
        f = ix.frame[s[i] : e[i]]
        u = ix.centers[f] - positions[j]
        q = center - positions[j]
        cos = u @ q / (np.linalg.norm(u, axis=1) * np.linalg.norm(q) + 1e-12)
        order = np.argsort(-cos)
        out[i] = f[order[min(_rank[0], len(order) - 1)]]
    return out


def aligned(self, q, pose, inl, kp, t):
    tol = {"rendered-agree": 0.25, "rendered-agree-0.5": 0.5}.get(self.config.descriptors.split("|")[0])
    if tol is None:
        return orig_aligned(self, q, pose, inl, kp, t)
    from favormap.localize.align import blurred_gray

    if q.gray is None:
        q.gray = blurred_gray(q.image, self._aligner.config.sigma)
    out = []
    for r in (0, 1):
        _rank[0] = r
        out.append(orig_align(self._aligner, q.gray, q.cam.K, pose, self.positions, inl[:, 0], kp))
    _rank[0] = 0
    (m0, ok0), (m1, ok1) = out
    keep = ok0 & ok1 & (np.linalg.norm(m0 - m1, axis=1) <= tol)
    return np.where(keep[:, None], (m0 + m1) / 2, kp)


PlaneAligner.reference_frames = reference_frames
LL.Localizer._aligned = aligned
import favormap.localize as L  # noqa: E402
from favormap.localize import descriptors as D  # noqa: E402

orig_source = D.make_source


def make_source(name, m, device="cpu", obs=None):
    return orig_source(name.split("-agree")[0], m, device, obs)


D.make_source = L.make_source = make_source
B.VARIANTS["rendered agree"] = ("rendered-agree", {"align": True})
B.VARIANTS["rendered agree-0.5"] = ("rendered-agree-0.5", {"align": True})

if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    B.main()
