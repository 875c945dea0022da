# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
"""Landmark accuracy as the queries see it: residual at the GT query pose to the query keypoint matched
by projection (<= R px) + descriptor (>= S)."""
import numpy as np
from favormap.geometry import project
from favormap.build import extract_sequence, ExtractorSpec

def query_features(qseq):
    return extract_sequence(qseq, ExtractorSpec("sift", 2048), 640)

def residuals(qff, positions, D, R=4.0, S=0.8):
    out = []
    Ks = [c.K for c in qff.cameras]
    for f in range(len(qff.features)):
        F = qff.features[f]
        uv, z = project(Ks[f], qff.cam_from_world[f], positions, with_depth=True)
        W, H = F.image_size
        c = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < W) & (uv[:, 1] < H))
        s = D[c] @ F.descriptors.T
        d = np.linalg.norm(uv[c, None] - F.keypoints[None], axis=2)
        s[d > R] = -1
        k = s.argmax(1)
        ok = s[np.arange(len(c)), k] >= S
        out.append(np.stack([np.full(ok.sum(), f), c[ok], d[np.arange(len(c)), k][ok]], 1))
    return np.concatenate(out)

def summary(res, name):
    r = res[:, 2]
    return f"{name}: n={len(r)} median {np.median(r):.3f} px, <=1px {np.mean(r<=1):.3f}, p90 {np.percentile(r,90):.2f}"
