"""Landmarks refined by a localized stream (favormap.localize.stream) and the 'stream' prior mode."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from favormap.geometry import perturb_pose, pose_error, project


@pytest.fixture()
def localizer(small_map):
    from favormap.localize import Localizer

    _, path = small_map
    loc = Localizer(str(path))
    yield loc
    loc.close()


def _stream(loc, frames, refinement, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for fr in frames:
        res = loc.localize(fr.image_path, perturb_pose(fr.cam_from_world, 0.05, 3.0, rng))
        assert res.success, res.message
        out.append((res, refinement.update(res)))
    return out


def test_refinement_moves_the_landmarks_a_frame_saw_and_leaves_the_map_alone(localizer, small_sequence):
    from favormap.localize.stream import LandmarkRefinement

    before = np.array(localizer.map.positions, copy=True)
    ref = LandmarkRefinement(localizer, min_uncertainty_px=0.0)
    assert localizer.positions is ref.positions
    out = _stream(localizer, small_sequence.frames[4:8], ref)
    moved = np.unique(np.concatenate([m for _, m in out]))
    assert ref.frames_used == 4 and ref.updates > 0 and len(moved) > 20
    for res, m in out:  # every moved landmark was an inlier of that frame
        inl = np.asarray(res.matches)[np.asarray(res.inlier_mask, bool)][:, 0]
        assert np.isin(m, inl).all()
    assert np.any(ref.positions[moved] != before[moved])
    untouched = np.setdiff1d(np.arange(len(before)), moved)
    np.testing.assert_array_equal(ref.positions[untouched], before[untouched])
    np.testing.assert_array_equal(localizer.map.positions, before)  # the map's own array is not written
    # the refined landmarks still project onto their stream keypoints at the true poses (sub-pixel noise)
    res, m = out[-1]
    inl = np.asarray(res.matches)[np.asarray(res.inlier_mask, bool)]
    uv = project(res.camera.K, small_sequence.frames[7].cam_from_world, ref.positions[inl[:, 0]])
    assert np.median(np.linalg.norm(uv - res.keypoints[inl[:, 1]], axis=1)) < 0.5
    ref.close()
    assert localizer.positions is localizer.map.positions


def test_refinement_pulls_a_landmark_with_a_wrong_depth_back(localizer, small_sequence):
    """Landmarks pushed 3 % along their viewing ray (a depth error) come back towards where their
    mapping and stream observations put them."""
    from favormap.geometry import camera_centers
    from favormap.localize.stream import LandmarkRefinement

    ref = LandmarkRefinement(localizer, min_uncertainty_px=0.0)
    truth = np.array(ref.positions, copy=True)
    rows = np.arange(0, len(truth), 3)
    c = camera_centers(localizer.map.cam_from_world[:1])[0]
    ray = truth[rows] - c
    ref.positions[rows] = truth[rows] + 0.03 * ray
    out = _stream(localizer, small_sequence.frames[5:8], ref)
    moved = np.intersect1d(rows, np.concatenate([m for _, m in out]))
    assert len(moved) >= 10
    err_before = np.linalg.norm(0.03 * (truth[moved] - c), axis=1)
    err_after = np.linalg.norm(ref.positions[moved] - truth[moved], axis=1)
    assert np.median(err_after) < 0.2 * np.median(err_before)
    ref.close()


def test_a_wrong_observation_cannot_drag_a_landmark_out_of_its_box(localizer, small_sequence):
    """A 'localized' frame that matches landmark 0 to a keypoint 80 px from where it projects: the
    triangulation either drops that observation or moves the landmark far, and a move beyond half a
    voxel box is refused."""
    from favormap.localize.stream import LandmarkRefinement

    ref = LandmarkRefinement(localizer, min_uncertainty_px=0.0)
    before = np.array(ref.positions, copy=True)
    fr = small_sequence.frames[6]
    cam = localizer.prepare(fr.image_path)[1]
    rows = np.arange(4)
    uv = project(cam.K, fr.cam_from_world, before[rows])
    uv[0] += 80.0
    fake = SimpleNamespace(
        success=True,
        cam_from_world=fr.cam_from_world,
        image_cam_from_world=fr.cam_from_world,
        camera=cam,
        keypoints=uv,
        matches=np.stack([rows, rows], 1),
        inlier_mask=np.ones(4, bool),
    )
    for _ in range(5):  # five such frames: the wrong observations outnumber none of the mapping ones
        moved = ref.update(fake)
        assert 0 not in moved or np.linalg.norm(ref.positions[0] - before[0]) <= 0.5 * localizer.map.voxel_size[0]
    assert np.linalg.norm(ref.positions[0] - before[0]) <= 0.5 * localizer.map.voxel_size[0]
    ref.close()


def test_landmarks_the_frame_sees_as_certain_are_left_alone(localizer, small_sequence):
    """The gate: a landmark is refined only where its map covariance, projected into the frame, is at
    least ``min_uncertainty_px``; the small room's long, exact tracks stay below a few pixels."""
    from favormap.localize.stream import LandmarkRefinement

    before = np.array(localizer.map.positions, copy=True)
    ref = LandmarkRefinement(localizer, min_uncertainty_px=5.0)
    out = _stream(localizer, small_sequence.frames[4:7], ref)
    assert ref.updates == 0 and all(len(m) == 0 for _, m in out)
    np.testing.assert_array_equal(ref.positions, before)
    ref.close()
    low = LandmarkRefinement(localizer, min_uncertainty_px=0.0)
    _stream(localizer, small_sequence.frames[4:7], low)
    assert low.updates > 0
    low.close()


def test_stream_prior_mode_evaluates_a_sequence(small_map, small_sequence):
    from favormap.localize import Localizer
    from favormap.localize.evaluate import EvalConfig, evaluate

    _, path = small_map
    loc = Localizer(str(path))
    try:
        seq = small_sequence.subset(range(3, 9))
        rep = evaluate({"rendered": loc}, seq, EvalConfig(prior_mode="stream"))[0]
    finally:
        loc.close()
    assert rep.summary["localized"] == 6 and rep.summary["false_successes"] == 0
    assert rep.summary["median_translation"] < 0.01
    assert loc.positions is loc.map.positions  # the refinement ended with the evaluation
    errs = [pose_error(o.result.cam_from_world, o.gt)[0] for o in rep.outcomes]
    assert max(errs) < 0.02


def test_a_sequence_refines_each_frames_landmarks_before_the_next_frame_uses_them(small_map, small_sequence):
    """localize_sequence triangulates the landmarks a frame refines while the next frame's features are
    extracted: frame by frame, the poses and matches of localizing one frame after the other with each
    frame's refinement applied before the next (Stream.update), with the positions refined by the time a
    frame is localized."""
    from favormap.localize import Localizer
    from favormap.localize.stream import Stream

    _, path = small_map
    frames = small_sequence.frames[3:9]
    first = perturb_pose(frames[0].cam_from_world, 0.05, 3.0, np.random.default_rng(2))
    loc = Localizer(str(path))
    try:
        want, moved = [], []
        with Stream(loc, first) as stream:
            for fr in frames:
                want.append(loc.localize(fr.image_path, stream.prior()))
                moved.append(stream.update(want[-1]))
        assert sum(len(m) for m in moved[:-1]) > 0  # the frames before the last did refine landmarks
        got, refined = [], []
        for res in loc.localize_sequence([fr.image_path for fr in frames], first):
            got.append(res)
            refined.append(not np.array_equal(loc.positions, loc.map.positions))
    finally:
        loc.close()
    assert refined[0] is False and all(refined[2:])  # frame k sees what frames before k refined
    for a, b in zip(want, got):
        assert a.success and b.success
        np.testing.assert_array_equal(a.cam_from_world, b.cam_from_world)
        np.testing.assert_array_equal(a.matches, b.matches)
    assert loc.positions is loc.map.positions


def test_a_sequence_reads_and_extracts_the_next_image_while_it_localizes_one(small_map, small_sequence, tmp_path):
    """localize_sequence asks for image k+1 (and extracts its features) before it gives frame k's result; an
    image that cannot be read fails with its own error when its turn comes, after every frame before it."""
    import time

    from favormap.errors import InputError
    from favormap.localize import Localizer

    _, path = small_map
    frames = small_sequence.frames[3:6]
    asked = []

    def images():
        for fr in frames:
            asked.append(fr.image_path)
            yield fr.image_path
        asked.append("missing")
        yield tmp_path / "missing.png"

    loc = Localizer(str(path))
    try:
        seq = loc.localize_sequence(images(), frames[0].cam_from_world)
        got = []
        for k in range(len(frames)):
            got.append(next(seq))
            deadline = time.monotonic() + 10
            while len(asked) < k + 2 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert len(asked) == k + 2  # the next image was taken while frame k was localized
        assert all(r.success for r in got)
        with pytest.raises(InputError, match="image not found"):
            next(seq)
    finally:
        loc.close()
    assert loc.positions is loc.map.positions  # the stream gave the map's landmarks back
