"""Eighteenth session: a track's keypoints aligned to its middle observation through the homography
of the landmark's local plane (the plane through the triangulated point, facing the reference camera,
or with the scene's true normal), then re-triangulated: does it move landmarks onto the surface?

python docs/benchmarks/s18-prototypes/plane_lk.py      (the small synthetic room, exact poses)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))
from conftest import SMALL  # noqa: E402

from favormap.build import BuildConfig, ExtractorSpec, extract_sequence, track_frames, triangulate_tracks  # noqa: E402
from favormap.geometry import camera_centers  # noqa: E402
from favormap.synthetic import make_room, surface_distance, write_sequence  # noqa: E402
from favormap.triangulation import refine_observations  # noqa: E402


def main():
    seq = write_sequence("/tmp/s18-plane-lk", depth=False, **SMALL)
    cfg = BuildConfig(max_keypoints=1024, max_side=0)
    ff = extract_sequence(seq, ExtractorSpec("sift", 1024), 0)
    grays = [ff.features[f].dense.gray for f in range(len(ff.features))]
    Ks, Ts = np.stack([c.K for c in ff.cameras]), ff.cam_from_world
    scene = make_room(SMALL["seed"])
    lms0 = triangulate_tracks(track_frames(ff, cfg), ff, cfg)
    X = lms0.positions

    def report(name, t):
        lms = triangulate_tracks(t, ff, cfg)
        d = np.abs(surface_distance(scene, lms.positions))
        print(f"{name:<34} landmarks {len(lms)}  surface distance median {np.median(d):.5f} mean {d.mean():.5f} p90 {np.percentile(d, 90):.5f}  reproj {np.median(lms.mean_reproj_error):.3f} px")

    def plane(normals=None, window=9, k=12):
        return refine_observations(lms0, grays, Ks, Ts, window, normal_k=k, normals=normals)

    report("SIFT keypoints", lms0.tracks)
    # translation-only Lucas-Kanade (tracking.refine_keypoints, removed after it lost on the fox;
    # commit e11195f): median 0.00878, p90 0.03709
    tr = lms0.tracks
    n_front = camera_centers(Ts)[tr.frame_idx[tr.offsets[:-1] + tr.lengths // 2]] - X
    n_front /= np.linalg.norm(n_front, axis=1, keepdims=True)
    for window in (9, 15):
        t, moved = plane(n_front, window)
        report(f"plane LK, fronto-parallel, {window} px (moved {moved.mean():.2f})", t)
    # normals from the landmarks themselves: PCA of the k nearest (triangulation.landmark_normals)
    for k in (8, 12, 20):
        t, moved = plane(None, 9, k)
        report(f"plane LK, PCA-{k} normal, 9 px (moved {moved.mean():.2f})", t)
    # the true normal: the surface's gradient of the distance field at the landmark
    eps = 1e-3
    grad = np.stack([(surface_distance(scene, X + eps * e) - surface_distance(scene, X - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
    n_true = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    for window in (9, 15):
        t, moved = plane(n_true, window)
        report(f"plane LK, true normal, {window} px (moved {moved.mean():.2f})", t)


if __name__ == "__main__":
    main()
