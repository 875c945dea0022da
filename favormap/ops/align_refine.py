"""Refining a map alignment over both maps' observations (the second stage of
:func:`favormap.ops.align.align_maps`).

Landmark positions are triangulated from few views and carry most of their error along the viewing
rays; the keypoints they were triangulated from, and the frame poses they were seen from, are far more
exact. Given a first similarity (from the landmarks), this stage

1. matches the landmarks again, guided: a b-landmark moved into a and the a-landmarks within a radius
   of it, the best descriptor among them kept when it passes the ratio test against the second best
   and the match is mutual;
2. refines the similarity and one 3D point per match jointly, over the reprojection errors of the
   point in every frame of either map that observed its landmark (a's frames as they are, b's frames
   moved by the similarity): Gauss-Newton with a Cauchy loss, the points eliminated (Schur
   complement), so that the similarity is fixed by rays, not by the landmarks' noisy depths; matches
   whose residuals stay far above the others' are dropped and the problem solved again;
3. states the similarity's uncertainty by a delete-one-block jackknife over the frames: each map's
   frames in consecutive blocks (pose errors of neighbouring frames are alike), the refinement solved
   again without each block's observations; the spread of those solutions gives the standard
   deviations (per axis of the translation, the rotation angle, log-scale).

Every array here is in a's frame unless named after b."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import rotation_angle_deg, rotvec_to_rotmat, transform_points
from ..least_squares import rotation_jacobian, schur_step


@dataclass
class MapObservations:
    """What the refinement reads of one map: its landmarks and every observation of them as a ray of
    the frame that saw it."""

    positions: np.ndarray  # (L, 3) landmark positions
    descriptors: np.ndarray  # (L, C) unit mean descriptors
    landmark_index: np.ndarray  # (O,) landmark of each observation
    frame_index: np.ndarray  # (O,) frame of each observation
    rays: np.ndarray  # (O, 2) normalised image coordinates (x / z, y / z) of the keypoint
    focal: np.ndarray  # (O,) pixels per normalised unit of the observing working camera
    cam_from_world: np.ndarray  # (M, 4, 4) frame poses
    reproj_error: np.ndarray  # (L,) mean reprojection error of each landmark in its own map, pixels

    @classmethod
    def read(cls, m) -> MapObservations:
        """The observations of an open :class:`favormap.mapfile.Map`."""
        from ..io.images import working_camera

        li, fi, xy = m.tracks()
        cams = np.asarray(m.frame_camera_ids)[fi]
        rays = np.zeros((len(xy), 2))
        focal = np.zeros(len(xy))
        for cid, cam in m.cameras.items():
            sel = cams == cid
            K = working_camera(cam, m.max_side).K
            rays[sel] = (xy[sel] - K[:2, 2]) / np.diag(K)[:2]
            focal[sel] = 0.5 * (K[0, 0] + K[1, 1])
        d = m.mean_descriptors(np.arange(len(m)))
        return cls(
            positions=np.asarray(m.positions, np.float64),
            descriptors=d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12),
            landmark_index=np.asarray(li, np.int64),
            frame_index=np.asarray(fi, np.int64),
            rays=rays,
            focal=focal,
            cam_from_world=np.asarray(m.cam_from_world, np.float64),
            reproj_error=np.asarray(m.reproj_error, np.float64),
        )


@dataclass
class RefinedAlignment:
    """The refined ``b_to_a``, the matches it rests on and its jackknife uncertainty."""

    b_to_a: np.ndarray  # (4, 4) similarity, x_a = b_to_a x_b
    matches: np.ndarray  # (K, 2) landmark rows (a, b) kept
    points: np.ndarray  # (K, 3) the refined point of each match, in a
    num_observations: int  # reprojection residuals (observations of the kept matches in both maps)
    reprojection_rms_px: float  # RMS reprojection error of the kept matches' observations
    std_translation_xyz: np.ndarray  # (3,) jackknife std of b_to_a's translation per axis, a's units
    std_rotation_deg: float  # jackknife RMS rotation difference, degrees
    std_log_scale: float  # jackknife std of log(scale)
    blocks: int  # frame blocks of the jackknife


# -------------------------------------------------------------------------------------------------
# guided matching
# -------------------------------------------------------------------------------------------------
def guided_matches(
    a: MapObservations, b: MapObservations, b_to_a: np.ndarray, radius: float, ratio: float, chunk: int = 200_000
) -> np.ndarray:
    """(K, 2) landmark rows (a, b): for each b-landmark moved into a, the a-landmark within ``radius`` of
    best descriptor similarity, kept when its descriptor distance is below ``ratio`` times the second
    best's within the radius (or it is the only one) and no other b-landmark claims it with a higher
    similarity."""
    from scipy.spatial import cKDTree

    pb = transform_points(b_to_a, b.positions)
    pairs = cKDTree(pb).sparse_distance_matrix(cKDTree(a.positions), radius, output_type="ndarray")
    jb, ia = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    if len(jb) == 0:
        return np.zeros((0, 2), np.int64)
    score = np.concatenate(
        [
            np.einsum("kc,kc->k", b.descriptors[jb[s : s + chunk]], a.descriptors[ia[s : s + chunk]])
            for s in range(0, len(jb), chunk)
        ]
    )
    order = np.lexsort((-score, jb))  # by b, best first
    jb, ia, score = jb[order], ia[order], score[order]
    starts = np.flatnonzero(np.r_[True, jb[1:] != jb[:-1]])
    has_second = np.diff(np.r_[starts, len(jb)]) >= 2
    d1 = np.sqrt(np.maximum(2 - 2 * score[starts], 0))
    second = np.where(has_second, score[np.minimum(starts + 1, len(score) - 1)], -1.0)
    d2 = np.sqrt(np.maximum(2 - 2 * second, 0))
    ok = ~has_second | (d1 < ratio * d2)
    jb, ia, score = jb[starts][ok], ia[starts][ok], score[starts][ok]
    # mutual: each a-landmark keeps its most similar b-landmark
    order = np.lexsort((-score, ia))
    jb, ia = jb[order], ia[order]
    keep = np.r_[True, ia[1:] != ia[:-1]]
    return np.stack([ia[keep], jb[keep]], 1)


# -------------------------------------------------------------------------------------------------
# the joint refinement
# -------------------------------------------------------------------------------------------------
@dataclass
class _Problem:
    """The observations of the matched landmarks, stacked: a's first, then b's."""

    point: np.ndarray  # (N,) match row of each observation
    frame: np.ndarray  # (N,) frame row in its own map
    from_b: np.ndarray  # (N,) bool
    cam_from_world: np.ndarray  # (N, 4, 4) pose of the observing frame in its own map
    rays: np.ndarray  # (N, 2)
    focal: np.ndarray  # (N,)
    block: np.ndarray  # (N,) jackknife block (a's blocks, then b's)

    @classmethod
    def of(cls, a: MapObservations, b: MapObservations, matches: np.ndarray, blocks: int) -> _Problem:
        parts = []
        for side, (m, rows) in enumerate(((a, matches[:, 0]), (b, matches[:, 1]))):
            where = np.full(len(m.positions), -1, np.int64)
            where[rows] = np.arange(len(rows))
            k = where[m.landmark_index]
            sel = k >= 0
            f = m.frame_index[sel]
            n_frames = len(m.cam_from_world)
            block = np.minimum(f * blocks // max(n_frames, 1), blocks - 1) + side * blocks
            parts.append(
                (k[sel], f, np.full(sel.sum(), side == 1), m.cam_from_world[f], m.rays[sel], m.focal[sel], block)
            )
        return cls(*(np.concatenate(x) for x in zip(*parts)))


def _points_in_frames(P: _Problem, X: np.ndarray, a_to_b: np.ndarray):
    """Each observation's point in its own map's frame (b's observations through ``a_to_b``)."""
    W = X[P.point]
    return np.where(P.from_b[:, None], transform_points(a_to_b, W), W)


def _residuals(P: _Problem, X: np.ndarray, a_to_b: np.ndarray) -> np.ndarray:
    Y = _points_in_frames(P, X, a_to_b)
    xc = (P.cam_from_world[:, :3, :3] @ Y[:, :, None])[:, :, 0] + P.cam_from_world[:, :3, 3]
    z = np.where(np.abs(xc[:, 2]) > 1e-12, xc[:, 2], 1e-12)
    return (xc[:, :2] / z[:, None] - P.rays) * P.focal[:, None]


def _cost(r: np.ndarray, c: float, weight: np.ndarray) -> float:
    return float(np.sum(weight * c * c * np.log1p(np.sum(r * r, 1) / (c * c))))


def _step(P: _Problem, X: np.ndarray, a_to_b: np.ndarray, c: float, weight: np.ndarray, damping: float):
    """One damped Gauss-Newton step of the Cauchy-weighted problem: (d_similarity (7,), d_points (K, 3)).
    The similarity's update is a left perturbation of ``a_to_b``: (rotation vector, translation,
    log-scale)."""
    K = len(X)
    Y = _points_in_frames(P, X, a_to_b)
    R_f, t_f = P.cam_from_world[:, :3, :3], P.cam_from_world[:, :3, 3]
    xc = (R_f @ Y[:, :, None])[:, :, 0] + t_f
    z = xc[:, 2]
    u = xc[:, :2] / z[:, None]
    r = (u - P.rays) * P.focal[:, None]
    w = weight / (1.0 + np.sum(r * r, 1) / (c * c))  # Cauchy IRLS weights
    # d residual / d point in its own frame: focal / z [[1, 0, -u], [0, 1, -v]] R_f
    dproj = np.zeros((len(z), 2, 3))
    dproj[:, 0, 0] = dproj[:, 1, 1] = 1.0
    dproj[:, :, 2] = -u
    J_Y = (P.focal / z)[:, None, None] * (dproj @ R_f)
    sR = a_to_b[:3, :3]
    J_X = np.where(P.from_b[:, None, None], J_Y @ sR, J_Y)
    dY = np.zeros((len(z), 3, 7))  # d Y / d (rotation vector, translation, log-scale)
    dY[:, :, :3] = rotation_jacobian(Y)
    dY[:, :, 3:6] = np.eye(3)
    dY[:, :, 6] = Y
    J_S = np.where(P.from_b[:, None, None], J_Y @ dY, 0.0)
    return schur_step(J_S, J_X, r, w, P.point, K, damping)


def _apply(a_to_b: np.ndarray, d_S: np.ndarray) -> np.ndarray:
    D = np.eye(4)
    D[:3, :3] = np.exp(d_S[6]) * rotvec_to_rotmat(d_S[:3])
    D[:3, 3] = d_S[3:6]
    return D @ a_to_b


def _solve(P: _Problem, X: np.ndarray, a_to_b: np.ndarray, c: float, weight: np.ndarray, iterations: int):
    """Levenberg-Marquardt on the Cauchy cost: (a_to_b, X)."""
    damping = 1e-4
    cost = _cost(_residuals(P, X, a_to_b), c, weight)
    for _ in range(iterations):
        d_S, d_X = _step(P, X, a_to_b, c, weight, damping)
        T_new, X_new = _apply(a_to_b, d_S), X + d_X
        new = _cost(_residuals(P, X_new, T_new), c, weight)
        if new < cost:
            a_to_b, X = T_new, X_new
            converged = cost - new < 1e-9 * cost
            cost, damping = new, max(damping / 4, 1e-8)
            if converged:
                break
        else:
            damping *= 10
            if damping > 1e4:
                break
    return a_to_b, X


def refine_alignment(
    a: MapObservations,
    b: MapObservations,
    matches: np.ndarray,
    b_to_a: np.ndarray,
    *,
    iterations: int = 30,
    outlier_factor: float = 3.0,
    blocks: int = 8,
    uncertainty: bool = True,
) -> RefinedAlignment:
    """The similarity ``b_to_a`` refined over the reprojection errors of the matched landmarks' points in
    both maps' frames (module docstring); ``matches`` (K, 2) landmark rows (a, b). Without
    ``uncertainty`` the jackknife is left out and the stds are infinite."""
    a_to_b = np.linalg.inv(b_to_a)
    X = 0.5 * (a.positions[matches[:, 0]] + transform_points(b_to_a, b.positions[matches[:, 1]]))
    P = _Problem.of(a, b, matches, blocks)
    ones = np.ones(len(P.point))
    c = max(2.0 * float(np.median(np.linalg.norm(_residuals(P, X, a_to_b), axis=1))), 0.5)
    a_to_b, X = _solve(P, X, a_to_b, c, ones, iterations)
    # drop the matches whose residuals stay far above the others', solve again
    r2 = np.sum(_residuals(P, X, a_to_b) ** 2, 1)
    per_match = np.sqrt(np.bincount(P.point, r2, len(X)) / np.maximum(np.bincount(P.point, None, len(X)), 1))
    keep = per_match <= outlier_factor * np.median(per_match)
    matches, X = matches[keep], X[keep]
    P = _Problem.of(a, b, matches, blocks)
    ones = np.ones(len(P.point))
    c = max(2.0 * float(np.median(np.linalg.norm(_residuals(P, X, a_to_b), axis=1))), 0.5)
    a_to_b, X = _solve(P, X, a_to_b, c, ones, iterations)
    r = _residuals(P, X, a_to_b)
    # delete-one-block jackknife, each solve started at the full solution
    used = np.unique(P.block)
    sols = [np.linalg.inv(_solve(P, X, a_to_b, c, (P.block != k).astype(float), 4)[0]) for k in used if uncertainty]
    return RefinedAlignment(
        b_to_a=np.linalg.inv(a_to_b),
        matches=matches,
        points=X,
        num_observations=len(r),
        reprojection_rms_px=float(np.sqrt(np.mean(np.sum(r * r, 1)))),
        **_jackknife_std(np.asarray(sols).reshape(-1, 4, 4), np.linalg.inv(a_to_b)),
        blocks=len(used),
    )


def _jackknife_std(solutions: np.ndarray, b_to_a: np.ndarray) -> dict:
    """Jackknife standard deviations of the similarity from its delete-one-block solutions (n, 4, 4):
    sqrt((n - 1) / n * sum of squared deviations from their mean) per component."""
    n = len(solutions)
    if n < 2:
        return {"std_translation_xyz": np.full(3, np.inf), "std_rotation_deg": np.inf, "std_log_scale": np.inf}
    f = (n - 1) / n
    s = np.cbrt(np.linalg.det(solutions[:, :3, :3]))
    s0 = np.cbrt(np.linalg.det(b_to_a[:3, :3]))
    t = solutions[:, :3, 3]
    R = solutions[:, :3, :3] / s[:, None, None]
    ang = rotation_angle_deg(R @ (b_to_a[:3, :3] / s0).T)
    return {
        "std_translation_xyz": np.sqrt(f * np.sum((t - t.mean(0)) ** 2, 0)),
        "std_rotation_deg": float(np.sqrt(f * np.sum(ang**2))),
        "std_log_scale": float(np.sqrt(f * np.sum((np.log(s) - np.log(s).mean()) ** 2))),
    }
