"""Damped Gauss-Newton steps of problems with a few shared parameters and many 3D points (bundle
adjustment's structure): the points' 3 x 3 blocks are eliminated by the Schur complement, so a step
solves one small system whatever the number of points. NumPy, batched over the observations; used by
the map alignment's refinement (favormap.ops.align_refine) and the build's camera rotation
(favormap.pose_refinement)."""

from __future__ import annotations

import numpy as np

from .geometry import sum_by_group


def rotation_jacobian(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3): d (R v) / d (rotation vector) at R = I for points ``v`` (N, 3), i.e. -[v]x."""
    J = np.zeros((len(v), 3, 3))
    J[:, 0, 1], J[:, 0, 2] = v[:, 2], -v[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -v[:, 2], v[:, 0]
    J[:, 2, 0], J[:, 2, 1] = v[:, 1], -v[:, 0]
    return J


def schur_step(
    J_S: np.ndarray,
    J_X: np.ndarray,
    r: np.ndarray,
    w: np.ndarray,
    point: np.ndarray,
    n_points: int,
    damping: float,
    point_ridge: float = 0.0,
    shared_ridge: float = 1e-12,
) -> tuple[np.ndarray, np.ndarray]:
    """One Levenberg-Marquardt step (d_shared (p,), d_points (n_points, 3)) of the weighted least squares
    with residuals ``r`` (N, 2), their Jacobians ``J_S`` (N, 2, p) in the shared parameters and ``J_X``
    (N, 2, 3) in the position of their point ``point`` (N,), and weights ``w`` (N,) (a robust loss's
    IRLS weights). Both diagonals are damped by ``damping`` times themselves; ``point_ridge`` times a
    block's mean diagonal (plus 1e-12) keeps a point seen along parallel rays solvable, ``shared_ridge``
    the reduced system."""
    p = J_S.shape[2]
    wJ_S, wJ_X = w[:, None, None] * J_S, w[:, None, None] * J_X
    H_SS = wJ_S.reshape(-1, p).T @ J_S.reshape(-1, p)
    g_S = wJ_S.reshape(-1, p).T @ r.reshape(-1)
    wJ_S_T, wJ_X_T = np.swapaxes(wJ_S, 1, 2), np.swapaxes(wJ_X, 1, 2)
    H_SX = sum_by_group(wJ_S_T @ J_X, point, n_points)
    H_XX = sum_by_group(wJ_X_T @ J_X, point, n_points)
    g_X = sum_by_group((wJ_X_T @ r[:, :, None])[:, :, 0], point, n_points)
    ridge = point_ridge * np.trace(H_XX, axis1=1, axis2=2)[:, None, None] / 3 + 1e-12 if point_ridge else 1e-12
    H_XX = H_XX + damping * H_XX * np.eye(3) + ridge * np.eye(3)
    H_XX_inv = np.linalg.inv(H_XX)
    V = H_SX @ H_XX_inv
    H_red = H_SS + damping * np.diag(np.diag(H_SS)) - (V @ np.swapaxes(H_SX, 1, 2)).sum(0)
    g_red = g_S - (V @ g_X[:, :, None])[:, :, 0].sum(0)
    d_S = -np.linalg.solve(H_red + shared_ridge * np.eye(p), g_red)
    d_X = -(H_XX_inv @ (g_X + np.swapaxes(H_SX, 1, 2) @ d_S)[:, :, None])[:, :, 0]
    return d_S, d_X
