"""The alignment's refinement over both maps' observations, on synthetic observations with known truth:
landmarks whose depths are noisy along their viewing rays, keypoints with pixel noise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from favormap.geometry import look_at, rotation_angle_deg, rotvec_to_rotmat, transform_points, umeyama
from favormap.ops.align import align_observations
from favormap.ops.align_config import AlignConfig
from favormap.ops.align_refine import MapObservations, guided_matches, refine_alignment

FOCAL = 500.0


def _observations(points, cam_from_world, rng, depth_noise, pixel_noise) -> MapObservations:
    """Every point seen by every camera; landmark positions moved along the first camera's ray."""
    L, M = len(points), len(cam_from_world)
    li, fi = np.repeat(np.arange(L), M), np.tile(np.arange(M), L)
    xc = np.einsum("nij,nj->ni", cam_from_world[fi, :3, :3], points[li]) + cam_from_world[fi, :3, 3]
    rays = xc[:, :2] / xc[:, 2:3] + rng.normal(scale=pixel_noise / FOCAL, size=(len(li), 2))
    centre = -cam_from_world[0, :3, :3].T @ cam_from_world[0, :3, 3]
    along = points - centre
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    noisy = points + along * rng.normal(scale=depth_noise, size=(L, 1))
    desc = rng.normal(size=(L, 32))
    return MapObservations(
        positions=noisy,
        descriptors=desc / np.linalg.norm(desc, axis=1, keepdims=True),
        landmark_index=li,
        frame_index=fi,
        rays=rays,
        focal=np.full(len(li), FOCAL),
        cam_from_world=cam_from_world,
        reproj_error=np.full(L, pixel_noise),
    )


def _cameras(centres, target):
    return np.stack([look_at(c, target) for c in centres])


@pytest.fixture(scope="module")
def pair():
    """(a, b, b_to_a): 300 points on a box 4 units in front of two camera paths, b's frame moved by a
    similarity; landmark depths off by 5 % of the distance, keypoints by 0.5 px."""
    rng = np.random.default_rng(3)
    points = rng.uniform([-2, -1.5, 3], [2, 1.5, 5], size=(300, 3))
    target = np.array([0.0, 0.0, 4.0])
    path_a = np.c_[np.linspace(-1.0, 0.2, 8), np.zeros(8), np.zeros(8)]
    path_b = np.c_[np.linspace(-0.2, 1.0, 8), np.full(8, 0.3), np.full(8, 0.2)]
    T = np.eye(4)
    T[:3, :3] = 1.7 * rotvec_to_rotmat(np.array([0.3, -0.5, 0.2]))
    T[:3, 3] = [0.5, -2.0, 1.0]
    a = _observations(points, _cameras(path_a, target), rng, 0.2, 0.5)
    # b: the same points, seen from its own path, all in b's frame (x_b = T^-1 x_a)
    Ti = np.linalg.inv(T)
    b = _observations(points, _cameras(path_b, target), rng, 0.2, 0.5)
    b.cam_from_world = b.cam_from_world @ T
    b.cam_from_world[:, :3, :] /= np.cbrt(np.linalg.det(T[:3, :3]))
    b.positions = transform_points(Ti, b.positions)
    b.descriptors = a.descriptors + 0.05 * rng.normal(size=a.descriptors.shape)
    b.descriptors /= np.linalg.norm(b.descriptors, axis=1, keepdims=True)
    return a, b, T


def _errors(T_est, T):
    s, s_true = np.cbrt(np.linalg.det(T_est[:3, :3])), np.cbrt(np.linalg.det(T[:3, :3]))
    rot = float(rotation_angle_deg((T_est[:3, :3] / s) @ (T[:3, :3] / s_true).T))
    return rot, abs(np.log(s / s_true)), np.abs(T_est[:3, 3] - T[:3, 3])


def test_rays_fix_the_similarity_far_better_than_noisy_landmark_positions(pair):
    a, b, T = pair
    matches = np.stack([np.arange(300), np.arange(300)], 1)
    coarse = umeyama(b.positions, a.positions)
    rot0, ls0, t0 = _errors(coarse, T)
    r = refine_alignment(a, b, matches, coarse)
    rot, ls, t = _errors(r.b_to_a, T)
    assert rot < 0.2 * rot0 and ls < 0.2 * ls0 and np.linalg.norm(t) < 0.2 * np.linalg.norm(t0), (rot0, rot, ls0, ls)
    assert rot < 0.05 and ls < 5e-4
    # keypoint noise of 0.5 px: the refined points reproject to about that
    assert 0.3 < r.reprojection_rms_px < 1.0
    # the jackknife std covers the error, and is not inflated far beyond it
    assert rot <= 3 * r.std_rotation_deg and ls <= 3 * r.std_log_scale
    assert np.all(t <= 3 * r.std_translation_xyz)
    assert r.std_rotation_deg < 0.05 and r.std_log_scale < 1e-3


def test_wrong_matches_are_dropped_and_do_not_move_the_similarity(pair):
    a, b, T = pair
    rng = np.random.default_rng(0)
    matches = np.stack([np.arange(300), np.arange(300)], 1)
    wrong = rng.choice(300, 30, replace=False)
    matches[wrong, 1] = np.roll(matches[wrong, 1], 1)  # 10 % of the pairs swapped
    r = refine_alignment(a, b, matches, umeyama(b.positions, a.positions))
    kept = {tuple(m) for m in r.matches.tolist()}
    assert not any((int(i), int(j)) in kept for i, j in matches[wrong]), "a wrong match survived"
    rot, ls, _ = _errors(r.b_to_a, T)
    assert rot < 0.05 and ls < 5e-4


def test_guided_matches_find_the_pairs_near_each_moved_landmark(pair):
    a, b, T = pair
    m = guided_matches(a, b, T, radius=0.5, ratio=0.9)
    assert len(m) >= 280
    assert np.mean(m[:, 0] == m[:, 1]) > 0.99
    # each a-landmark at most once
    assert len(np.unique(m[:, 0])) == len(m)
    # nothing within a radius that holds no landmark
    assert (
        len(guided_matches(a, b, T @ np.diag([1, 1, 1, 1.0]) + np.c_[np.zeros((4, 3)), [100, 0, 0, 0]], 0.5, 0.9)) == 0
    )


def test_maps_whose_poses_disagree_are_aligned_with_a_warning(pair):
    a, b, T = pair
    voxel_size = np.full(len(a.positions), 0.2)
    r = align_observations(a, b, voxel_size, AlignConfig())
    assert r.warnings == []
    assert _errors(r.b_to_a, T)[0] < 0.05
    # b's frames each turned by 1 degree about a random axis: its poses no longer fit a's images
    rng = np.random.default_rng(1)
    turned = dataclasses.replace(b, cam_from_world=b.cam_from_world.copy())
    for P in turned.cam_from_world:
        axis = rng.normal(size=3)
        P[:3, :] = rotvec_to_rotmat(np.radians(1.0) * axis / np.linalg.norm(axis)) @ P[:3, :]
    r = align_observations(a, turned, voxel_size, AlignConfig())
    assert len(r.warnings) == 1 and "poses disagree" in r.warnings[0], r.warnings
