"""tools/diagnose_accuracy.py on synthetic correspondences with a known truth: residuals at the
truth, the oracle PnP, the plain refinement, common inliers and the triangulation angle."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import diagnose_accuracy as diag  # noqa: E402

from favormap.geometry import look_at, perturb_pose, project  # noqa: E402
from favormap.io import Camera  # noqa: E402


@dataclass
class FakeResult:
    success: bool
    cam_from_world: np.ndarray
    keypoints: np.ndarray
    matches: np.ndarray
    inlier_mask: np.ndarray
    camera: Camera
    by_projection: np.ndarray | None = None


def scene(seed=0, n=300, bad=60, shift_px=3.0):
    rng = np.random.default_rng(seed)
    cam = Camera("PINHOLE", 640, 480, np.array([500.0, 500.0, 320.0, 240.0]))
    gt = look_at(np.array([0.0, 0.0, -4.0]), np.zeros(3))
    X = rng.uniform(-1.5, 1.5, (n, 3))
    uv = project(cam.K, gt, X)
    kp = uv + rng.normal(0, 0.2, uv.shape)
    kp[:bad] += shift_px * np.stack([np.cos(a := rng.uniform(0, 2 * np.pi, bad)), np.sin(a)], 1)
    return cam, gt, X, kp


def test_fit_query_separates_accurate_and_shifted_points_and_the_oracle_recovers_the_truth():
    cam, gt, X, kp = scene()
    est = perturb_pose(gt, 0.02, 0.3, np.random.default_rng(1))
    proj = np.zeros(len(X), bool)
    proj[:60] = True  # the shifted ones, as if found by projection
    res = FakeResult(True, est, kp, np.c_[np.arange(len(X)), np.arange(len(X))], np.ones(len(X), bool), cam, proj)
    pts = diag.PointSet(X, np.full(len(X), 4), np.full(len(X), 10.0), np.zeros(0), np.zeros(0, np.int64))
    prior = perturb_pose(gt, 0.3, 10.0, np.random.default_rng(2))
    f = diag.fit_query("q", gt, res, pts, [1.0], prior)
    assert f.inliers == len(X)
    assert np.median(f.gt_px[60:]) < 0.35 and np.min(f.gt_px[:60]) > 2.0
    kept, t_err, _ = f.oracle[1.0]
    assert kept == pytest.approx(240, abs=5)  # the accurate points, not the shifted ones
    assert t_err < 0.01 < f.t_err  # the estimate started 0.02 away
    assert f.plain_t_err < f.t_err  # the plain refinement of all inliers moves towards the truth
    assert 20 <= f.cells <= 48 and f.prior_t == pytest.approx(0.3, rel=1e-6)
    s = diag.landmark_summary([f], pts)
    assert s["query_gt_by_projection"]["median"] > 2.0 > s["query_gt_by_descriptor"]["median"]
    assert s["query_gt_offset_px"] == pytest.approx([0.0, 0.0], abs=0.1)


def test_common_inliers_pair_the_same_keypoints():
    cam, gt, X, kp = scene(bad=0)
    res = FakeResult(True, gt, kp, np.c_[np.arange(len(X)), np.arange(len(X))], np.ones(len(X), bool), cam)
    pts = diag.PointSet(X, np.full(len(X), 4), np.full(len(X), 10.0), np.zeros(0), np.zeros(0, np.int64))
    moved = diag.PointSet(X + [0.01, 0, 0], pts.track_length, pts.angle_deg, pts.mapping_error_px, pts.mapping_point)
    a = diag.fit_query("q", gt, res, pts, [])
    b = diag.fit_query("q", gt, res, moved, [])
    c = diag.common_inliers([a], [b])
    assert c["pairs"] == len(X) and c["keypoint_offset_median_px"] == 0.0
    assert c["point_offset_median_px"] == pytest.approx(500 * 0.01 / 4, rel=0.3)  # 1 cm at ~4 m, f = 500 px


def test_point_set_angle_and_mapping_error():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.array([[0.0, 0.0, 0.0]])
    poses = np.stack([look_at(np.array([x, 0.0, -2.0]), np.zeros(3)) for x in (-1.0, 1.0)])
    xy = np.stack([project(K, T, X)[0] for T in poses]) + [[0.5, 0.0], [0.0, 0.0]]
    ps = diag.point_set(X, [0, 0], [0, 1], xy, poses, np.stack([K, K]))
    assert ps.angle_deg[0] == pytest.approx(2 * np.degrees(np.arctan(0.5)), abs=1e-6)  # the two rays' angle
    assert ps.mapping_error_px == pytest.approx([0.5, 0.0], abs=1e-9)
    assert ps.track_length.tolist() == [2]
