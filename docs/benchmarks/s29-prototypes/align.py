"""Twenty-ninth session: query keypoints aligned photometrically to the landmark's appearance in a
mapping image, warped into the query through the landmark's local plane (PTAM / SVO-style feature
alignment), before the final weighted refinement.

Why: on the synthetic orbit (docs/benchmarks/s29-prototypes/decomp.py) the query's SIFT keypoints sit
0.1-1 px from the surface point the mapping keypoints were detected on, the shift growing with the
angle and shared by the inliers; replacing each inlier's keypoint by the projection of that surface
point (ground truth) takes the orbit from 0.00052 to 0.00035 units (pycolmap refinement from the true
pose). This prototype does it from images: the landmark's nearest-angle observation's neighbourhood
(p x p pixels of the query around the landmark's predicted projection, carried through the plane
through the landmark with a PCA normal of its nearest landmarks into that mapping image), then
Lucas-Kanade for a 2D shift with gain and offset in the query image.

Variants for tools/bench_accuracy.py: ``rendered align`` (aligned keypoints replace the inliers' own
where the alignment converged), ``rendered align-drop`` (inliers that did not converge leave the
final refinement), ``rendered align-fp`` (fronto-parallel plane to the reference camera instead of the
PCA normal). Run from the repository root:

    PYTHONPATH=. FAVORMAP_FOX=../shared/data/fox python docs/benchmarks/s29-prototypes/align.py \
        --workdir /tmp/acc28f --reuse --splits orbit --priors noise --no-baseline \
        --variants "rendered,rendered align"
"""

import os
import sys
import threading
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2] / "tools"))
import bench_accuracy as B  # noqa: E402

import favormap.localize as L  # noqa: E402
import favormap.localize.localizer as LL  # noqa: E402
from favormap.geometry import camera_centers, inverse, project  # noqa: E402
from favormap.io import load_image, read_sequence  # noqa: E402
from favormap.localize import descriptors as D  # noqa: E402

HALF = int(os.environ.get("ALIGN_HALF", 5))  # patch (2 HALF + 1)^2
SIGMA = float(os.environ.get("ALIGN_SIGMA", 1.0))  # Gaussian blur of both images
MIN_NCC = float(os.environ.get("ALIGN_NCC", 0.8))
MAX_SHIFT = float(os.environ.get("ALIGN_SHIFT", 2.0))
ITERS = 15
STATS = []

_state = threading.local()
orig_source, orig_weighted, orig_prepare = D.make_source, LL.Localizer._weighted, LL.Localizer.prepare


def make_source(name, m, device="cpu", obs=None):
    return orig_source(name.split("-align")[0], m, device, obs)


def prepare(self, image, camera=None):
    img, cam = orig_prepare(self, image, camera)
    _state.img = img
    return img, cam


def gray(img):
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32) if img.ndim == 3 else img.astype(np.float32)
    return cv2.GaussianBlur(g, (0, 0), SIGMA) if SIGMA > 0 else g


class MapImages:
    """The map's mapping frames (working resolution, blurred grey), its landmarks' normals."""

    def __init__(self, loc):
        m = loc.map
        data = m.load()
        src = Path(data.provenance["source"])
        seq = read_sequence(src)
        by_name = {f.name: f for f in seq.frames}
        self.images = []
        for name in data.frame_names:
            fr = by_name[name]
            img, _ = load_image(fr.image_path, seq.cameras[fr.camera_id], data.max_side)
            self.images.append(gray(img))
        self.data = data
        from favormap.io.images import working_camera

        self.K = [working_camera(data.cameras[int(c)], data.max_side).K for c in data.frame_camera_ids]
        X = data.positions
        from scipy.spatial import cKDTree

        _, nn = cKDTree(X).query(X, k=13)
        P = X[nn] - X[nn].mean(1, keepdims=True)
        _, _, vt = np.linalg.svd(P, full_matrices=False)
        n = vt[:, 2]
        C = camera_centers(data.cam_from_world)
        toward = np.zeros_like(X)
        np.add.at(toward, data.track_landmark, C[data.track_frame] - X[data.track_landmark])
        n *= np.sign(np.sum(n * toward, 1, keepdims=True))
        self.normals = n
        self.C = C
        order = np.argsort(data.track_landmark, kind="stable")
        self.obs = order
        self.start = np.searchsorted(data.track_landmark[order], np.arange(len(X) + 1))


def _maps(loc):
    mi = getattr(loc, "_align_images", None)
    if mi is None:
        mi = loc._align_images = MapImages(loc)
    return mi


def sample(img, uv):
    """bilinear samples of img at COLMAP-convention pixel positions uv (..., 2)"""
    sh = uv.shape[:-1]
    flat = uv.reshape(-1, 2).astype(np.float32) - 0.5
    m = len(flat)
    w = 1024
    pad = np.full(((m + w - 1) // w * w, 2), -10.0, np.float32)
    pad[:m] = flat
    pad = pad.reshape(-1, w, 2)
    out = cv2.remap(img, pad[..., 0], pad[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out.reshape(-1)[:m].reshape(sh)


NREF = int(os.environ.get("ALIGN_NREF", 1))


def align(loc, T, K, rows, kp, fronto=False):
    """Aligned positions (N, 2) and a converged mask for landmarks ``rows`` matched to ``kp``: the mean
    of the alignments to the landmark's NREF nearest-angle observations that converged."""
    mi = _maps(loc)
    d = mi.data
    X = d.positions[rows]
    Cq = camera_centers(T)
    uq = Cq - X
    uq /= np.linalg.norm(uq, axis=1, keepdims=True)
    refs = np.full((len(rows), NREF), -1, np.int64)
    for i, j in enumerate(rows):
        o = mi.obs[mi.start[j] : mi.start[j + 1]]
        v = mi.C[d.track_frame[o]] - X[i]
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        best = o[np.argsort(-(v @ uq[i]))[:NREF]]
        refs[i, : len(best)] = d.track_frame[best]
    acc, cnt = np.zeros((len(rows), 2)), np.zeros(len(rows))
    for k in range(NREF):
        has = refs[:, k] >= 0
        moved, conv = _align_one(mi, T, K, X[has], refs[has, k], kp[has], fronto, rows[has])
        idx = np.flatnonzero(has)[conv]
        acc[idx] += moved[conv]
        cnt[idx] += 1
    conv = cnt > 0
    moved = np.where(conv[:, None], acc / np.maximum(cnt, 1)[:, None], kp)
    STATS.append((len(rows), int(conv.sum()), float(np.median(np.linalg.norm(moved - kp, axis=1)[conv])) if conv.any() else np.nan))
    return moved, conv


def _align_one(mi, T, K, X, ref, kp, fronto, rows):
    d = mi.data
    Iq = gray(_state.img)
    gy_q, gx_q = np.gradient(Iq)
    Cq = camera_centers(T)
    n = mi.normals[rows].copy()
    if fronto:
        n = mi.C[ref] - X
        n /= np.linalg.norm(n, axis=1, keepdims=True)
    u0 = project(K, T, X)
    g = np.arange(-HALF, HALF + 1, dtype=np.float64)
    off = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)  # (P, 2)
    u = u0[:, None, :] + off[None]  # (N, P, 2)
    Rinv = T[:3, :3].T
    ray = np.concatenate([(u - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(u.shape[:2] + (1,))], -1) @ Rinv.T
    t = np.sum(n * (X - Cq), 1)[:, None] / np.einsum("npk,nk->np", ray, n)
    P = Cq + t[..., None] * ray  # (N, P, 3)
    tmpl = np.full(u.shape[:2], np.nan, np.float32)
    for f in np.unique(ref):
        s = ref == f
        uv = project(mi.K[f], d.cam_from_world[f], P[s].reshape(-1, 3)).reshape(-1, len(off), 2)
        tmpl[s] = sample(mi.images[f], uv)
    ok = np.all(np.isfinite(tmpl), 1) & np.all(t > 0, 1)
    tmpl = np.nan_to_num(tmpl)
    shift = np.zeros((len(rows), 2))
    gain, bias = np.ones(len(rows)), np.zeros(len(rows))
    for _ in range(ITERS):
        us = u + shift[:, None]
        Iv, gx, gy = sample(Iq, us), sample(gx_q, us), sample(gy_q, us)
        bad = ~np.all(np.isfinite(Iv), 1)
        ok &= ~bad
        Iv, gx, gy = np.nan_to_num(Iv), np.nan_to_num(gx), np.nan_to_num(gy)
        r = Iv - (gain[:, None] * tmpl + bias[:, None])
        J = np.stack([gx, gy, -tmpl, -np.ones_like(tmpl)], -1)  # (N, P, 4)
        H = np.einsum("npi,npj->nij", J, J) + 1e-6 * np.eye(4)
        b = -np.einsum("npi,np->ni", J, r)
        delta = np.linalg.solve(H, b[..., None])[..., 0]
        shift += delta[:, :2]
        gain += delta[:, 2]
        bias += delta[:, 3]
    us = u + shift[:, None]
    Iv = np.nan_to_num(sample(Iq, us))
    a = Iv - Iv.mean(1, keepdims=True)
    bt = tmpl - tmpl.mean(1, keepdims=True)
    ncc = np.sum(a * bt, 1) / np.sqrt(np.sum(a * a, 1) * np.sum(bt * bt, 1) + 1e-12)
    moved = u0 + shift
    conv = ok & (ncc >= MIN_NCC) & (np.linalg.norm(moved - kp, axis=1) <= MAX_SHIFT)
    return moved, conv


def weighted(self, q, it, last, t):
    name = self.config.descriptors
    if "-align" not in name:
        return orig_weighted(self, q, it, last, t)
    inl_idx = np.flatnonzero(last["inliers"])
    inl = last["matches"][inl_idx]
    kp_all = q.feats.keypoints
    moved, conv = align(self, it.cam_from_world, q.cam.K, inl[:, 0], kp_all[inl[:, 1]], fronto=name.endswith("-fp"))
    new = kp_all.copy()
    new[inl[conv, 1]] = moved[conv]
    last2 = last
    if name.endswith("-drop"):
        last2 = dict(last)
        mask = last["inliers"].copy()
        mask[inl_idx[~conv]] = False
        last2["inliers"] = mask
    feats = q.feats
    old = feats.keypoints
    try:
        object.__setattr__(feats, "keypoints", new)
        return orig_weighted(self, q, it, last2, t)
    finally:
        object.__setattr__(feats, "keypoints", old)


D.make_source = L.make_source = make_source
LL.Localizer._weighted = weighted
LL.Localizer.prepare = prepare
for v in ("align", "align-drop", "align-fp"):
    B.VARIANTS[f"rendered {v}"] = (f"rendered-{v}", {})
    B.VARIANTS[f"mean {v}"] = (f"mean-{v}", {})

if __name__ == "__main__":
    sys.argv[0] = "bench_accuracy.py"
    try:
        B.main()
    finally:
        if STATS:
            s = np.array(STATS, float)
            print(f"alignment: {len(s)} refinements, converged {s[:, 1].sum() / s[:, 0].sum():.2f} of the inliers, "
                  f"median move {np.nanmedian(s[:, 2]):.2f} px", file=sys.stderr)
