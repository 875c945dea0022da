"""Prototype: DISK query keypoints moved to where the query's dense descriptor field best matches the
landmark's rendered descriptor (within +-R px), then the pose localized again from the first pose;
the control localizes again from the first pose without the moves; "gated" keeps the second pose
only where its inliers' median reprojection residual is below the first pose's. From the repository root:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox [R=2] [STEP=0.25] [GATE=0.0] [CONE=0] \
        python docs/benchmarks/s21-prototypes/kpref.py fox-holdout /tmp/acc19/fox-holdout-disk.h5

GATE: keep a move only where the peak lies inside the window and gains at least GATE in cosine over
the keypoint's own position; CONE: only landmarks seen within their training view cone + CONE deg."""
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_accuracy as B
from favormap.localize import Localizer, LocalizeConfig
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.mapfile import Map
from favormap.features.base import Features

split_name, map_path = sys.argv[1], sys.argv[2]
R = float(os.environ.get("R", 2.0)); STEP = float(os.environ.get("STEP", 0.25))
sp = [s for s in B.fox_splits([split_name]) if s.name == split_name][0]
m = Map.open(map_path)
loc = Localizer(m, LocalizeConfig())
ex = loc.extractor
priors = make_priors(sp.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
g = np.arange(-R, R + 1e-9, STEP)
off = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2).astype(np.float32)


def terr(T, gt):
    c = lambda T: -T[:3, :3].T @ T[:3, 3]
    return np.linalg.norm(c(T) - c(gt))


class Fixed:
    def __init__(self, f): self.f = f
    def extract(self, img): return self.f
    def __getattr__(self, n): return getattr(ex, n)


e0, e1, e2, e3, acc, moved = [], [], [], [], [], []
for fr, prior in zip(sp.queries.frames, priors):
    cam = sp.queries.cameras[fr.camera_id]
    img, wcam = loc.prepare(fr.image_path, cam)
    feats = ex.extract(img)
    loc.extractor = Fixed(feats)
    r1 = loc.localize(fr.image_path, prior, cam)
    if not r1.success:
        print(fr.name, "failed"); loc.extractor = ex; continue
    mt = np.asarray(r1.matches)[np.asarray(r1.inlier_mask, bool)]
    rows, kidx = mt[:, 0], mt[:, 1]
    rend = loc.source(rows, r1.cam_from_world, {})
    kp = np.asarray(feats.keypoints, np.float32)
    pts = (kp[kidx][:, None, :] + off[None]).reshape(-1, 2)
    d = ex.sample(feats, pts).reshape(len(kidx), len(off), -1)
    sim = np.einsum("nkc,nc->nk", d, rend)
    am = sim.argmax(1)
    best = off[am].copy()
    GATE = os.environ.get("GATE", "")
    if GATE:  # keep a move only where the peak lies inside the window and beats the keypoint's own similarity
        centre = np.argmin(np.linalg.norm(off, axis=1))
        edge = np.abs(off[am]).max(1) >= R - 1e-6
        gain = sim[np.arange(len(am)), am] - sim[:, centre]
        best[edge | (gain < float(GATE))] = 0
    CONE = os.environ.get("CONE", "")
    if CONE:  # only landmarks seen from inside their training view cone (+ CONE deg)
        C = -r1.cam_from_world[:3, :3].T @ r1.cam_from_world[:3, 3]
        v = C - np.asarray(m.positions)[rows]
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        ang = np.degrees(np.arccos(np.clip(np.sum(v * np.asarray(m.view_dir)[rows], 1), -1, 1)))
        best[ang > np.asarray(m.view_angle)[rows] + float(CONE)] = 0
    kp2 = kp.copy(); kp2[kidx] += best
    moved.append(np.median(np.linalg.norm(best, axis=1)))
    f2 = Features(kp2, feats.scores, feats.descriptors, feats.image_size, feats.dense)
    loc.extractor = Fixed(f2)
    r2 = loc.localize(fr.image_path, r1.cam_from_world, cam)
    loc.extractor = Fixed(feats)
    r0 = loc.localize(fr.image_path, r1.cam_from_world, cam)
    e0.append(terr(r0.cam_from_world, fr.cam_from_world) if r0.success else np.nan)
    loc.extractor = ex
    def resid(r):
        mt_ = np.asarray(r.matches)[np.asarray(r.inlier_mask, bool)]
        X = np.asarray(m.positions)[mt_[:, 0]]
        Xc = X @ r.cam_from_world[:3, :3].T + r.cam_from_world[:3, 3]
        p = Xc @ np.asarray(r.camera.K).T
        uv = p[:, :2] / p[:, 2:3]
        return np.median(np.linalg.norm(uv - np.asarray(r.keypoints)[mt_[:, 1]], axis=1)), len(mt_)
    if r2.success:
        (q1, n1), (q2, n2) = resid(r1), resid(r2)
        acc.append(q2 < q1)
        e3.append(terr(r2.cam_from_world, fr.cam_from_world) if q2 < q1 else terr(r1.cam_from_world, fr.cam_from_world))
        print(f"   resid {q1:.3f} ({n1}) -> {q2:.3f} ({n2})")
    a, b = terr(r1.cam_from_world, fr.cam_from_world), terr(r2.cam_from_world, fr.cam_from_world) if r2.success else np.nan
    e1.append(a); e2.append(b)
    print(f"{fr.name} {a:.4f} -> {b:.4f}  moved med {moved[-1]:.2f} px  inl {r1.num_inliers if hasattr(r1,'num_inliers') else len(kidx)}", flush=True)
print("median first", np.median(e1), "again unmoved", np.nanmedian(e0), "moved", np.nanmedian(e2), "n", len(e1), "px", np.median(moved), "gated", np.median(e3), "accepted", np.sum(acc))
