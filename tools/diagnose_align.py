"""Why an alignment differs from a known transform: what the two maps' images say about the truth.

    PYTHONPATH=$PWD python tools/diagnose_align.py A.h5 B.h5 [--truth B_TO_A.txt]

``favormap.ops.align_maps`` fits the similarity to the keypoints of both maps' frames. When two maps'
poses share one frame (the truth is the identity, the default of ``--truth``) and the estimate still
differs from it by more than its stated uncertainty, either the method is wrong or the maps' poses
disagree with their images. This tool fits the refined matches' observations four ways, each with the
matched points free, and prints the robust (Cauchy) cost and the median reprojection error per map:

1. the similarity free (the estimate);
2. the similarity held at the truth;
3. the similarity held at the truth and one rigid offset on the camera side shared by every frame of both
   maps (a camera-to-body calibration error of the rig that recorded both: cam_from_world_true =
   offset @ cam_from_world);
4. the similarity and the offset both free.

If (2) costs far more than (1), the images contradict the truth as the poses state it; if (3) costs no
more than (1), one shared calibration offset (printed: angle and translation) explains the difference,
and an alignment from images cannot, and should not, return the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from favormap.geometry import rotation_angle_deg, rotvec_to_rotmat, transform_points  # noqa: E402
from favormap.least_squares import rotation_jacobian, schur_step  # noqa: E402
from favormap.mapfile import Map  # noqa: E402
from favormap.ops.align import align_maps  # noqa: E402
from favormap.ops.align_refine import (  # noqa: E402
    MapObservations,
    _apply,
    _points_in_frames,
    _Problem,
    _residuals,
    guided_matches,
    refine_alignment,
)


def fit(P: _Problem, X, a_to_b, offset, free_similarity: bool, free_offset: bool, c: float, iterations: int = 40):
    """Levenberg-Marquardt over (similarity (7), camera offset (6), points), the points eliminated;
    returns (X, a_to_b, offset, cost, residuals)."""

    def residuals(X, a_to_b, offset):
        Y = _points_in_frames(P, X, a_to_b)
        xc = (P.cam_from_world[:, :3, :3] @ Y[:, :, None])[:, :, 0] + P.cam_from_world[:, :3, 3]
        xc = xc @ offset[:3, :3].T + offset[:3, 3]
        return (xc[:, :2] / xc[:, 2:3] - P.rays) * P.focal[:, None], xc, Y

    def cost(r):
        return float(np.sum(c * c * np.log1p(np.sum(r * r, 1) / (c * c))))

    K, damping = len(X), 1e-4
    r, xc, Y = residuals(X, a_to_b, offset)
    current = cost(r)
    for _ in range(iterations):
        z = xc[:, 2]
        u = xc[:, :2] / z[:, None]
        w = 1 / (1 + np.sum(r * r, 1) / (c * c))
        dproj = np.zeros((len(z), 2, 3))
        dproj[:, 0, 0] = dproj[:, 1, 1] = 1
        dproj[:, :, 2] = -u
        Dp = (P.focal / z)[:, None, None] * dproj
        J_Y = Dp @ (offset[:3, :3] @ P.cam_from_world[:, :3, :3])
        J_X = np.where(P.from_b[:, None, None], J_Y @ a_to_b[:3, :3], J_Y)
        dY = np.concatenate([rotation_jacobian(Y), np.broadcast_to(np.eye(3), (len(Y), 3, 3)), Y[:, :, None]], 2)
        J_S = np.where(P.from_b[:, None, None], J_Y @ dY, 0.0) * free_similarity
        J_E = Dp @ np.concatenate([rotation_jacobian(xc), np.broadcast_to(np.eye(3), (len(xc), 3, 3))], 2) * free_offset
        J_G = np.concatenate([J_S, J_E], 2)
        d, dX = schur_step(J_G, J_X, r, w, P.point, K, damping, shared_ridge=1e-9)
        D = np.eye(4)
        D[:3, :3], D[:3, 3] = rotvec_to_rotmat(d[7:10]), d[10:13]
        trial = (X + dX, _apply(a_to_b, d[:7]), D @ offset)
        r_new, xc_new, Y_new = residuals(*trial)
        if cost(r_new) < current:
            (X, a_to_b, offset), (r, xc, Y), current = trial, (r_new, xc_new, Y_new), cost(r_new)
            damping = max(damping / 4, 1e-8)
        else:
            damping *= 10
    return X, a_to_b, offset, current, r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--truth", help="4x4 b_to_a text file (default: the identity)")
    args = ap.parse_args()
    truth = np.loadtxt(args.truth) if args.truth else np.eye(4)
    r = align_maps(args.a, args.b)
    with Map.open(args.a) as ma, Map.open(args.b) as mb:
        a, b = MapObservations.read(ma), MapObservations.read(mb)
    matches = refine_alignment(
        a, b, guided_matches(a, b, r.b_to_a, r.threshold, 0.9), r.b_to_a, uncertainty=False
    ).matches
    P = _Problem.of(a, b, matches, 1)
    X0 = 0.5 * (a.positions[matches[:, 0]] + transform_points(r.b_to_a, b.positions[matches[:, 1]]))
    c = 2.0 * float(np.median(np.linalg.norm(_residuals(P, X0, np.linalg.inv(r.b_to_a)), axis=1)))
    print(f"{len(matches)} matches, {len(P.point)} observations; Cauchy scale {c:.2f} px")
    rows = (
        ("similarity free", r.b_to_a, True, False),
        ("similarity = truth", truth, False, False),
        ("truth + shared camera offset", truth, False, True),
        ("similarity + camera offset free", r.b_to_a, True, True),
    )
    for name, T0, free_s, free_o in rows:
        X, a_to_b, offset, cost, res = fit(P, X0.copy(), np.linalg.inv(T0), np.eye(4), free_s, free_o, c)
        T = np.linalg.inv(a_to_b)
        s, s_true = np.cbrt(np.linalg.det(T[:3, :3])), np.cbrt(np.linalg.det(truth[:3, :3]))
        rot = float(rotation_angle_deg((T[:3, :3] / s) @ (truth[:3, :3] / s_true).T))
        n = np.linalg.norm(res, axis=1)
        print(
            f"{name:32s} cost {cost:10.0f}  median px a {np.median(n[~P.from_b]):.2f} b {np.median(n[P.from_b]):.2f}  "
            f"vs truth: rotation {rot:.3f} deg, scale {100 * (s / s_true - 1):+.3f} %, translation "
            + " ".join(f"{v:+.4f}" for v in T[:3, 3] - truth[:3, 3])
            + f"  offset {float(rotation_angle_deg(offset[:3, :3])):.3f} deg, "
            + " ".join(f"{v:+.4f}" for v in offset[:3, 3])
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
