"""Eighteenth session: a track's keypoints aligned to its middle observation through the homography
of the landmark's local plane (the plane through the triangulated point, facing the reference camera,
or with the scene's true normal), then re-triangulated: does it move landmarks onto the surface?

python docs/benchmarks/s18-prototypes/plane_lk.py      (the small synthetic room, exact poses)
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))
from conftest import SMALL  # noqa: E402

from favormap.build import BuildConfig, ExtractorSpec, extract_sequence, track_frames, triangulate_tracks  # noqa: E402
from favormap.geometry import camera_centers, project  # noqa: E402
from favormap.synthetic import make_room, surface_distance, write_sequence  # noqa: E402
from favormap.tracking import Tracks, refine_keypoints  # noqa: E402


def plane_points(K, T, pix, X, n):
    """World points where the rays of pixels ``pix`` (N, G, 2; COLMAP convention) of camera (K, T)
    meet the planes through X (N, 3) with normals n (N, 3)."""
    R, C = T[:3, :3], camera_centers(T)
    h = np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], -1)
    rays = np.einsum("ij,ngj->ngi", R.T @ np.linalg.inv(K), h)
    lam = np.einsum("ni,ni->n", n, X - C)[:, None] / np.einsum("ni,ngi->ng", n, rays)
    return C + lam[..., None] * rays


def sample(img, xy):
    """Bilinear samples of ``img`` at COLMAP-convention points xy (..., 2)."""
    shp = xy.shape[:-1]
    m = (xy.reshape(-1, 1, 2) - 0.5).astype(np.float32)
    out = cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(shp)


def plane_lk(tracks, grays, Ks, Ts, X, normals, half=7, iters=10, max_move=1.5):
    g = np.stack(np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1)), -1).reshape(-1, 2).astype(np.float64)
    lens = tracks.lengths
    ref = np.repeat(tracks.offsets[:-1] + lens // 2, lens)
    tid = tracks.track_of_obs
    xy = tracks.xy.copy()
    moved = np.zeros(len(xy), bool)
    grads = [(cv2.Sobel(im.astype(np.float32), cv2.CV_32F, 1, 0, ksize=1) * 0.5, cv2.Sobel(im.astype(np.float32), cv2.CV_32F, 0, 1, ksize=1) * 0.5) for im in grays]
    todo = np.flatnonzero(np.arange(len(xy)) != ref)
    for b in np.unique(tracks.frame_idx[todo]):
        obs = todo[tracks.frame_idx[todo] == b]
        for a in np.unique(tracks.frame_idx[ref[obs]]):
            o = obs[tracks.frame_idx[ref[obs]] == a]
            pa = tracks.xy[ref[o]]
            grid = pa[:, None] + g[None]
            A = sample(grays[a].astype(np.float32), grid)
            J = np.stack([sample(grads[a][0], grid), sample(grads[a][1], grid)], -1)  # (N, G, 2)
            J = J - J.mean(1, keepdims=True)
            Hs = np.einsum("ngi,ngj->nij", J, J) + 1e-6 * np.eye(2)
            A0 = A - A.mean(1, keepdims=True)
            s = np.zeros((len(o), 2))
            for _ in range(iters):
                P = plane_points(Ks[a], Ts[a], grid + s[:, None], X[tid[o]], normals[tid[o]])
                W = sample(grays[b].astype(np.float32), project(Ks[b], Ts[b], P.reshape(-1, 3)).reshape(P.shape[:-1] + (2,)))
                e = (W - W.mean(1, keepdims=True)) - A0
                s = s - np.linalg.solve(Hs, np.einsum("ngi,ng->ni", J, e)[..., None])[..., 0]
            pb = project(Ks[b], Ts[b], plane_points(Ks[a], Ts[a], (pa + s)[:, None], X[tid[o]], normals[tid[o]])[:, 0])
            ok = np.linalg.norm(pb - tracks.xy[o], axis=1) <= max_move
            xy[o[ok]] = pb[ok]
            moved[o[ok]] = True
    return Tracks(tracks.frame_idx, tracks.keypoint_idx, xy, tracks.offsets), moved


def main():
    seq = write_sequence("/tmp/s18-plane-lk", depth=False, **SMALL)
    cfg = BuildConfig(max_keypoints=1024, max_side=0)
    ff = extract_sequence(seq, ExtractorSpec("sift", 1024), 0)
    tr = track_frames(ff, cfg)
    grays = [ff.features[f].dense.gray for f in range(len(ff.features))]
    Ks, Ts = np.stack([c.K for c in ff.cameras]), ff.cam_from_world
    scene = make_room(SMALL["seed"])
    lms0 = triangulate_tracks(tr, ff, cfg)
    tr0 = lms0.tracks
    X = lms0.positions

    def report(name, t):
        lms = triangulate_tracks(t, ff, cfg)
        d = np.abs(surface_distance(scene, lms.positions))
        print(f"{name:<34} landmarks {len(lms)}  surface distance median {np.median(d):.5f} mean {d.mean():.5f} p90 {np.percentile(d, 90):.5f}  reproj {np.median(lms.mean_reproj_error):.3f} px")

    report("SIFT keypoints", tr0)
    report("Lucas-Kanade, translation (15 px)", refine_keypoints(tr0, grays, 15)[0])
    lens = tr0.lengths
    ref_frame = tr0.frame_idx[tr0.offsets[:-1] + lens // 2]
    n_front = camera_centers(Ts)[ref_frame] - X
    n_front /= np.linalg.norm(n_front, axis=1, keepdims=True)
    for half in (4, 7):
        t, moved = plane_lk(tr0, grays, Ks, Ts, X, n_front, half=half)
        report(f"plane LK, fronto-parallel, {2 * half + 1} px (moved {moved.mean():.2f})", t)
    # normals from the landmarks themselves: PCA of the k nearest (facing the reference camera)
    from scipy.spatial import cKDTree

    for k in (8, 12, 20):
        _, nn = cKDTree(X).query(X, k=k)
        Y = X[nn] - X[nn].mean(1, keepdims=True)
        w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", Y, Y))
        n_pca = v[:, :, 0] * np.sign(np.einsum("ni,ni->n", v[:, :, 0], n_front))[:, None]
        t, moved = plane_lk(tr0, grays, Ks, Ts, X, n_pca, half=4)
        report(f"plane LK, PCA-{k} normal, 9 px (moved {moved.mean():.2f})", t)
    # the true normal: the surface's gradient of the distance field at the landmark
    eps = 1e-3
    grad = np.stack([(surface_distance(scene, X + eps * e) - surface_distance(scene, X - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
    n_true = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    for half in (4, 7):
        t, moved = plane_lk(tr0, grays, Ks, Ts, X, n_true, half=half)
        report(f"plane LK, true normal, {2 * half + 1} px (moved {moved.mean():.2f})", t)


if __name__ == "__main__":
    main()
