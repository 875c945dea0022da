"""The paths real inputs take: images with lens distortion (OPENCV, like the fox data) resized for
mapping (max_side > 0), query cameras at other resolutions, and merging maps built at different
working resolutions. Every other test builds undistorted images at full size (max_side = 0)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from favormap.geometry import perturb_pose, pose_error
from favormap.io import Camera, working_camera

# 480x360, 60 deg horizontal field of view, barrel distortion of ~6 px at the corners
DISTORTED = Camera("OPENCV", 480, 360, [415.7, 415.7, 240.0, 180.0, -0.08, 0.02, 0.001, -0.001])
MAX_SIDE = 240


@pytest.fixture(scope="module")
def distorted_sequence(tmp_path_factory):
    from favormap.synthetic import write_sequence

    return write_sequence(tmp_path_factory.mktemp("seq_distorted"), n_frames=16, seed=0, camera=DISTORTED)


@pytest.fixture(scope="module")
def resized_map(distorted_sequence, tmp_path_factory):
    from conftest import small_build_config

    from favormap.build import build_map
    from favormap.mapfile import write_map

    m = build_map(distorted_sequence, small_build_config(max_side=MAX_SIDE, max_landmarks=300, iterations=80))
    path = tmp_path_factory.mktemp("map_resized") / "resized.h5"
    write_map(m, path)
    return m, path


def test_synthetic_images_show_the_lens_distortion(distorted_sequence):
    """The renderer applies the camera model: a world point projects to the pixel pycolmap's OPENCV
    model gives, and back-projection inverts it."""
    from favormap.synthetic import backproject, make_room, project, render_depth

    T = distorted_sequence.frames[3].cam_from_world
    depth = render_depth(make_room(0), DISTORTED, T)
    px = np.array([[10.5, 12.5], [470.5, 350.5], [240.5, 180.5], [100.5, 300.5]])
    z = depth[px[:, 1].astype(int), px[:, 0].astype(int)]
    X = backproject(DISTORTED, T, px, z)
    uv, zz = project(DISTORTED, T, X)
    np.testing.assert_allclose(uv, px, atol=1e-6)
    np.testing.assert_allclose(zz, z, rtol=1e-6)
    pinhole_uv, _ = project(DISTORTED.pinhole(), T, X)
    assert np.max(np.linalg.norm(pinhole_uv - px, axis=1)) > 4.0  # the corners really are distorted


def test_resized_undistorted_build_reprojects_and_lies_on_the_surface(resized_map, distorted_sequence):
    from favormap.synthetic import make_room, surface_distance

    m, _ = resized_map
    assert m.max_side == MAX_SIDE and m.num_landmarks >= 150
    work = working_camera(DISTORTED, MAX_SIDE)
    assert (work.width, work.height) == (240, 180) and work.model == "PINHOLE"
    assert np.median(m.reproj_error) < 0.5  # working pixels; a wrong undistortion gives several px
    # the tracks are keypoints at the working resolution: reprojecting with the working camera hits them
    from favormap.geometry import project

    uv = project(work.K, m.cam_from_world[m.track_frame], m.positions[m.track_landmark])
    assert np.median(np.linalg.norm(uv - m.track_xy, axis=1)) < 0.5
    d = surface_distance(make_room(0), m.positions)
    assert np.median(d) < 0.01, np.median(d)


@pytest.fixture(scope="module")
def distorted_queries(distorted_sequence):
    from favormap.synthetic import make_room, random_views_near, render

    scene = make_room(0)
    poses = [f.cam_from_world for f in distorted_sequence.frames]
    views = random_views_near(poses, 3, seed=5, max_trans=0.08, max_rot_deg=4.0, scene=scene)
    return [(render(scene, DISTORTED, T)[0], T) for T in views]


def test_distorted_queries_localize_on_the_resized_path(resized_map, distorted_queries):
    from favormap.localize import LocalizeConfig, Localizer

    _, path = resized_map
    loc = Localizer(path, LocalizeConfig(iterations=3))
    rng = np.random.default_rng(0)
    errs = []
    for img, T in distorted_queries:
        res = loc.localize(img, perturb_pose(T, 0.2, 10.0, rng), DISTORTED)
        assert res.success, res.message
        errs.append(pose_error(res.cam_from_world, T))
    errs = np.array(errs)
    assert np.median(errs[:, 0]) < 0.01 and np.median(errs[:, 1]) < 0.5, errs


def test_a_query_at_another_resolution_scales_its_camera(resized_map):
    """A query image twice the size of its camera's (same aspect ratio): the camera is scaled to
    the image, then to the map's working resolution; a query camera of another size entirely (here
    a pinhole 360x270 one) is scaled to the map's working resolution too."""
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.synthetic import make_room, render

    m, path = resized_map
    scene = make_room(0)
    T = m.cam_from_world[5]
    big = DISTORTED.scaled(960, 720)
    img_big = render(scene, big, T, ss=1)[0]
    small = Camera("PINHOLE", 360, 270, [311.8, 311.8, 180.0, 135.0])
    img_small = render(scene, small, T)[0]
    loc = Localizer(path, LocalizeConfig(iterations=2))
    prior = perturb_pose(T, 0.1, 5.0, np.random.default_rng(1))
    for img, cam in ((img_big, DISTORTED), (img_small, small)):
        res = loc.localize(img, prior, cam)
        assert res.success, res.message
        t, r = pose_error(res.cam_from_world, T)
        assert t < 0.01 and r < 0.5, (cam, t, r)


def test_merge_scales_track_pixels_to_the_first_maps_resolution(resized_map, tmp_path):
    """A map built at another working resolution: merged, its observations are converted to the
    first map's working pixels (they must land where the landmarks project there)."""
    from favormap.geometry import project
    from favormap.mapfile import Map, write_map
    from favormap.mapfile.model import new_landmark_ids
    from favormap.ops.merge import MergeConfig, merge_maps

    m, path_a = resized_map
    other_side = 160
    wb = working_camera(DISTORTED, other_side)
    xy_b = project(wb.K, m.cam_from_world[m.track_frame], m.positions[m.track_landmark]).astype(np.float32)
    b = dataclasses.replace(m, max_side=other_side, track_xy=xy_b, ids=new_landmark_ids(m.num_landmarks, avoid=m.ids))
    path_b = write_map(b, tmp_path / "b.h5")
    out = merge_maps([path_a, path_b], tmp_path / "ab.h5", MergeConfig(dedup=False)).path
    wa = working_camera(DISTORTED, MAX_SIDE)
    with Map.open(out) as mm:
        assert mm.max_side == MAX_SIDE
        tl, tf, xy = mm.tracks()
        from_b = tl >= m.num_landmarks
        assert from_b.sum() == len(m.track_xy)
        uv = project(wa.K, mm.cam_from_world[tf[from_b]], mm.positions[tl[from_b]])
        err = np.linalg.norm(uv - xy[from_b], axis=1)
        assert np.max(err) < 0.02, np.max(err)
        # and the first map's observations are untouched
        np.testing.assert_allclose(np.sort(xy[~from_b], axis=0), np.sort(m.track_xy, axis=0), atol=1e-4)
