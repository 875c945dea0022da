"""The evaluation's diagnostics (favormap.localize.evaluate) on synthetic correspondences."""

import numpy as np
import pycolmap

from favormap.geometry import from_rigid3d, look_at, pose_error, project, to_rigid3d
from favormap.io.types import Camera
from favormap.localize.evaluate import pose_noise_floor

CAM = Camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0])


def _scene(n, rng):
    gt = look_at(np.array([0.3, -0.2, -4.0]), np.zeros(3))
    X = rng.uniform(-1.5, 1.5, size=(n, 3))
    return gt, X, project(CAM.K, gt, X)


def _estimate(gt, X, kp):
    ans = pycolmap.refine_absolute_pose(to_rigid3d(gt), kp, X, np.ones(len(X), bool), CAM.to_pycolmap())
    return from_rigid3d(ans["cam_from_world"])


def test_the_noise_floor_predicts_the_error_of_correct_noisy_correspondences():
    rng = np.random.default_rng(0)
    gt, X, uv = _scene(150, rng)
    errors, floors, sigmas = [], [], []
    for trial in range(12):
        kp = uv + rng.normal(0.0, 0.8, uv.shape)
        est = _estimate(gt, X, kp)
        errors.append(pose_error(est, gt)[0])
        f = pose_noise_floor(CAM, est, X, kp, seed=trial)
        floors.append(f["noise_floor"])
        sigmas.append(f["residual_px"])
    # the residual scale is recovered from the residuals, and the floor is the size of the actual errors
    assert abs(np.median(sigmas) - 0.8) < 0.1
    assert 0.6 < np.median(errors) / np.median(floors) < 1.6


def test_the_noise_floor_falls_with_more_inliers_and_rises_with_larger_residuals():
    rng = np.random.default_rng(1)
    gt, X, uv = _scene(800, rng)
    noise = rng.normal(size=uv.shape)

    def floor(n, sigma):
        kp = uv[:n] + sigma * noise[:n]
        return pose_noise_floor(CAM, _estimate(gt, X[:n], kp), X[:n], kp, samples=40)["noise_floor"]

    few, many, noisy = floor(100, 0.5), floor(800, 0.5), floor(100, 1.5)
    assert 0.2 < many / few < 0.6  # ~ 1 / sqrt(8) = 0.35
    assert 2.0 < noisy / few < 4.5  # ~ 3
    # too few correspondences to say anything
    assert pose_noise_floor(CAM, gt, X[:5], uv[:5])["noise_floor"] is None
