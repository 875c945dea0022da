"""The camera's rotation against the given poses (favormap.pose_refinement.estimate_camera_rotation): one
turn shared by every frame, as a hand-eye calibration's error gives it, is found from the tracks, the
landmarks are triangulated with the camera's poses, and the map (frames/cam_from_rig) makes the localizer
take and report poses in the given poses' frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import small_build_config

from favormap.geometry import pose_error, rotation_about, rotation_angle_deg

TURN_DEG = 1.0


def _turned(seq, R: np.ndarray):
    """``seq`` with every pose turned on the camera side by ``R`` (the camera centres stay)."""
    frames = []
    for f in seq.frames:
        T = f.cam_from_world.copy()
        T[:3, :4] = R @ T[:3, :4]
        frames.append(dataclasses.replace(f, cam_from_world=T))
    return dataclasses.replace(seq, frames=frames)


def _turn() -> np.ndarray:
    return rotation_about(np.array([0.3, -1.0, 0.4]), np.radians(TURN_DEG))


@pytest.fixture(scope="module")
def turned_stages(small_sequence):
    """The build's stages up to triangulation on the small room whose poses are all turned by one degree."""
    from favormap.build import ExtractorSpec, extract_sequence, track_frames, triangulate_tracks

    cfg = small_build_config()
    ff = extract_sequence(small_sequence, ExtractorSpec("sift", cfg.max_keypoints), cfg.max_side)
    given = np.stack([f.cam_from_world for f in _turned(small_sequence, _turn()).frames])
    ff = dataclasses.replace(ff, cam_from_world=given)
    tracks = track_frames(ff, cfg)
    return cfg, ff, tracks, triangulate_tracks(tracks, ff, cfg)


def test_a_turn_every_given_pose_shares_is_found_from_the_tracks(turned_stages, small_sequence):
    """Poses turned by 1 deg on the camera side: the estimate undoes the turn to a tenth of a degree (what it
    finds on the exact poses, below), and the landmarks triangulated with the camera's poses fit their
    observations better."""
    from favormap.build import triangulate_tracks
    from favormap.pose_refinement import estimate_camera_rotation

    cfg, ff, tracks, lms = turned_stages
    est = estimate_camera_rotation(lms, ff.cam_from_world, ff.cameras)
    assert est.cam_from_rig.shape == (4, 4) and np.allclose(est.cam_from_rig[:3, 3], 0)
    # cam_from_rig @ given = the camera's pose: the inverse of the turn
    assert rotation_angle_deg(est.cam_from_rig[:3, :3] @ _turn()) < 0.1
    assert abs(est.angle_deg - TURN_DEG) < 0.1
    truth = np.stack([f.cam_from_world for f in small_sequence.frames])
    assert max(pose_error(a, b)[1] for a, b in zip(est.camera_poses(ff.cam_from_world), truth)) < 0.1
    again = triangulate_tracks(tracks, dataclasses.replace(ff, cam_from_world=est.camera_poses(ff.cam_from_world)), cfg)
    assert np.median(again.mean_reproj_error) < 0.8 * np.median(lms.mean_reproj_error)
    assert est.stats()["camera_rotation_deg"] == pytest.approx(est.angle_deg, abs=1e-3)
    # both halves of the frames find the same turn
    assert est.halves_apart_deg < 0.2 and est.holds and est.stats()["camera_rotation_applied"]


def test_poses_without_a_shared_turn_give_none(small_sequence):
    """The exact poses of the room: the estimated rotation stays below a tenth of a degree (a rendering's
    half-pixel conventions look like a turn of a few hundredths)."""
    from favormap.build import ExtractorSpec, extract_sequence, track_frames, triangulate_tracks
    from favormap.pose_refinement import estimate_camera_rotation

    cfg = small_build_config()
    ff = extract_sequence(small_sequence, ExtractorSpec("sift", cfg.max_keypoints), cfg.max_side)
    lms = triangulate_tracks(track_frames(ff, cfg), ff, cfg)
    assert estimate_camera_rotation(lms, ff.cam_from_world, ff.cameras).angle_deg < 0.1


def test_the_build_decides_from_the_poses_fit_unless_told():
    """None: estimated where the tracks' median epipolar distance exceeds the extractor's keypoint
    precision (SIFT: 1 px), never for a limit given instead of measured (NaN); True / False decide."""
    from favormap.build import BuildConfig, estimates_camera_rotation

    assert estimates_camera_rotation(BuildConfig(), 1.95)
    assert not estimates_camera_rotation(BuildConfig(), 0.5)
    assert not estimates_camera_rotation(BuildConfig(), float("nan"))
    assert estimates_camera_rotation(BuildConfig(camera_rotation=True), 0.5)
    assert not estimates_camera_rotation(BuildConfig(camera_rotation=False), 1.95)


@pytest.fixture(scope="module")
def turned_map(small_sequence, tmp_path_factory):
    """(path, given sequence) of a map built with the camera's rotation from the turned room."""
    from favormap.build import build_map
    from favormap.mapfile import write_map

    given = _turned(small_sequence, _turn())
    path = tmp_path_factory.mktemp("turned") / "turned.h5"
    write_map(build_map(given, small_build_config(camera_rotation=True)), path)
    return path, given


def test_the_map_stores_the_camera_s_poses_and_its_rotation(turned_map, small_sequence):
    """frames/cam_from_world holds the camera's poses (the truth, to the estimate's error), frames/cam_from_rig
    the rotation; rig_from_world gives back the poses the map was built from; a load keeps it."""
    from favormap.mapfile import Map

    path, given = turned_map
    truth = np.stack([f.cam_from_world for f in small_sequence.frames])
    with Map.open(path) as m:
        assert m.stored_cam_from_rig is not None
        assert abs(m.info()["camera_rotation_deg"] - TURN_DEG) < 0.1
        assert max(pose_error(a, b)[1] for a, b in zip(m.cam_from_world, truth)) < 0.1
        np.testing.assert_allclose(m.rig_from_world, np.stack([f.cam_from_world for f in given.frames]), atol=1e-9)
        np.testing.assert_allclose(m.load().cam_from_rig, m.cam_from_rig)
        assert m.provenance["stats"]["camera_rotation_deg"] == pytest.approx(m.info()["camera_rotation_deg"], abs=1e-3)


def test_the_localizer_takes_and_reports_poses_in_the_given_frame(turned_map, small_sequence):
    """A view localized from a prior in the given poses' frame: the reported pose lies in that frame (within
    0.2 deg of the given pose, 1 deg from the camera's), image_cam_from_world is the camera's pose."""
    from favormap.geometry import perturb_pose
    from favormap.localize import Localizer

    path, given = turned_map
    rng = np.random.default_rng(0)
    loc = Localizer(str(path))
    try:
        for k in (3, 9):
            f_true, f_given = small_sequence.frames[k], given.frames[k]
            prior = perturb_pose(f_given.cam_from_world, 0.05, 3.0, rng)
            res = loc.localize(f_true.image_path, prior, small_sequence.cameras[f_true.camera_id])
            assert res.success, res.message
            np.testing.assert_allclose(res.prior, prior)
            assert pose_error(res.cam_from_world, f_given.cam_from_world)[1] < 0.2
            assert pose_error(res.image_cam_from_world, f_true.cam_from_world)[1] < 0.2
            assert pose_error(res.cam_from_world, f_true.cam_from_world)[1] > 0.7
            assert all(pose_error(it.cam_from_world, f_given.cam_from_world)[1] < 3.5 for it in res.iterations)
    finally:
        loc.close()


def test_merge_refuses_maps_turned_differently_and_prune_keeps_the_rotation(turned_map, small_map, tmp_path):
    from favormap.errors import FavormapError
    from favormap.mapfile import Map
    from favormap.ops import merge_maps
    from favormap.ops.prune import prune_map

    path, _ = turned_map
    with pytest.raises(FavormapError, match="turned differently"):
        merge_maps([path, small_map[1]], tmp_path / "merged.h5")
    assert not (tmp_path / "merged.h5").exists()
    prune_map(path, tmp_path / "pruned.h5", max_landmarks=100)
    with Map.open(path) as a, Map.open(tmp_path / "pruned.h5") as b:
        np.testing.assert_allclose(b.cam_from_rig, a.cam_from_rig)


def test_the_halves_are_those_of_the_recording_s_course(small_sequence):
    """Poses turned one way in the first half of the recording and the other way in the second (no shared
    calibration) do not hold: the halves in the order the recording went find the two turns, 2 deg apart;
    halves of frames taken alternately from the whole course mix both turns alike and agree."""
    from favormap.build import ExtractorSpec, extract_sequence, track_frames, triangulate_tracks
    from favormap.pose_refinement import estimate_camera_rotation

    cfg = small_build_config()
    ff = extract_sequence(small_sequence, ExtractorSpec("sift", cfg.max_keypoints), cfg.max_side)
    n = len(ff.cam_from_world)
    given = ff.cam_from_world.copy()
    for i in range(n):
        given[i, :3, :4] = (_turn() if i < n // 2 else _turn().T) @ given[i, :3, :4]
    ff = dataclasses.replace(ff, cam_from_world=given)
    lms = triangulate_tracks(track_frames(ff, cfg), ff, cfg)
    course = estimate_camera_rotation(lms, given, ff.cameras, order=np.arange(n))
    alternate = estimate_camera_rotation(lms, given, ff.cameras, order=np.r_[0:n:2, 1:n:2])
    assert course.halves_apart_deg > 1.5 and not course.holds
    assert alternate.halves_apart_deg < 0.5 * course.halves_apart_deg
    assert np.allclose(alternate.cam_from_rig, course.cam_from_rig)  # the whole recording's estimate is one
