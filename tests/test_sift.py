"""SIFT extractor: keypoints described in their own scale/orientation, patches consistent with
them, rotation invariance, and a SIFT map that localizes (synthetic scenes only)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from favormap import features


@pytest.fixture(scope="module")
def room_image():
    from favormap.synthetic import camera_path, make_camera, make_room, render

    return render(make_room(0), make_camera(320, 240), camera_path(3)[1])[0]


def test_sampling_at_keypoints_reproduces_their_descriptors(room_image):
    ex = features.create("sift", max_keypoints=500)
    f = ex.extract(room_image)
    assert len(f) > 100 and f.descriptors.shape == (len(f), 128)
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    again = ex.sample(f, f.keypoints)
    assert np.mean(np.sum(again * f.descriptors, 1) > 0.999) > 0.99
    # a patch pixel next to a keypoint is described in that keypoint's frame: close to it
    near = ex.sample(f, f.keypoints + [1.0, 0.0])
    assert np.median(np.sum(near * f.descriptors, 1)) > 0.9


def test_all_orientations_keep_every_keypoint_opencv_finds_at_a_location(room_image):
    strongest = features.create("sift", max_keypoints=4096).extract(room_image)
    every = features.create("sift", max_keypoints=4096, orientations="all").extract(room_image)
    pos = lambda f: {tuple(p) for p in np.round(f.keypoints, 1).tolist()}  # noqa: E731
    assert pos(every) == pos(strongest)  # the same locations ...
    assert len(np.unique(np.round(strongest.keypoints, 1), axis=0)) == len(strongest)
    assert len(every) > 1.05 * len(strongest)  # ... with the extra orientations of some of them
    with pytest.raises(ValueError, match="orientations"):
        features.create("sift", orientations="some")


def test_a_lower_contrast_threshold_adds_weaker_keypoints_to_the_same_ones(room_image):
    """SIFTExtractor(contrast_threshold=...): the maps' default finds a subset of what a lower
    threshold finds (the extra keypoints are the weaker ones); a threshold must be a number > 0."""
    default = features.create("sift", max_keypoints=100_000).extract(room_image)
    low = features.create("sift", max_keypoints=100_000, contrast_threshold=0.005).extract(room_image)
    assert features.create("sift").contrast_threshold == 0.02
    assert len(low) > 1.1 * len(default)  # 1,196 against 1,035 on this image
    have = {tuple(p) for p in np.round(low.keypoints, 1).tolist()}
    assert np.mean([tuple(p) in have for p in np.round(default.keypoints, 1).tolist()]) > 0.95
    assert np.median(low.scores) < np.median(default.scores)
    for bad in (0, -0.01, float("nan"), "0.01"):
        with pytest.raises(ValueError, match="contrast_threshold"):
            features.create("sift", contrast_threshold=bad)


def test_the_orientation_kept_at_a_location_does_not_depend_on_the_rest_of_the_image(room_image):
    """Where OpenCV finds several orientations at one location they share a response, so a cap that
    reorders equal responses (OpenCV's nfeatures) changed which one "strongest" kept with the number
    of keypoints in the image. With the cap applied by extract() instead, every keypoint found at
    both thresholds is described alike, capped or not."""
    for cap in (300, 100_000):
        a = features.create("sift", max_keypoints=cap).extract(room_image)
        b = features.create("sift", max_keypoints=cap, contrast_threshold=0.01).extract(room_image)
        at = {tuple(p): d for p, d in zip(np.round(b.keypoints, 2).tolist(), b.descriptors)}
        common = [(d, at[tuple(p)]) for p, d in zip(np.round(a.keypoints, 2).tolist(), a.descriptors) if tuple(p) in at]
        assert len(common) > 0.5 * len(a)
        assert all(np.allclose(d1, d2, atol=1e-6) for d1, d2 in common), cap
    assert len(features.create("sift", max_keypoints=300).extract(room_image)) <= 300


def test_descriptors_survive_an_in_plane_rotation(room_image):
    """Rotate the image by 40 degrees: mutual nearest neighbours with the ratio test must mostly
    land on the rotated keypoint (an upright, fixed-size descriptor fails this)."""
    ex = features.create("sift", max_keypoints=800)
    h, w = room_image.shape[:2]
    M = cv2.getRotationMatrix2D((w / 2, h / 2), 40, 1.0)
    rot = cv2.warpAffine(room_image, M, (w, h), flags=cv2.INTER_LINEAR)
    a, b = ex.extract(room_image), ex.extract(rot)
    sim = a.descriptors @ b.descriptors.T
    best = sim.argmax(1)
    top2 = -np.sort(-sim, 1)[:, :2]
    ok = (sim.argmax(0)[best] == np.arange(len(a))) & (
        np.sqrt(np.maximum(2 - 2 * top2[:, 0], 0)) < 0.8 * np.sqrt(2 - 2 * top2[:, 1])
    )
    # where the keypoint must land (OpenCV pixel convention = COLMAP's minus 0.5)
    pa = np.c_[a.keypoints - 0.5, np.ones(len(a))] @ M.T + 0.5
    err = np.linalg.norm(pa[ok] - b.keypoints[best[ok]], axis=1)
    assert ok.sum() >= 50, ok.sum()
    assert np.mean(err < 2.0) > 0.85, np.mean(err < 2.0)


def _correct_matches(a, b, M, ex_ratio=0.8, tol=2.0):
    sim = a.descriptors @ b.descriptors.T
    best = sim.argmax(1)
    top2 = -np.sort(-sim, 1)[:, :2]
    ok = (sim.argmax(0)[best] == np.arange(len(a))) & (
        np.sqrt(np.maximum(2 - 2 * top2[:, 0], 0)) < ex_ratio * np.sqrt(2 - 2 * top2[:, 1])
    )
    pa = np.c_[a.keypoints - 0.5, np.ones(len(a))] @ M.T + 0.5
    return int(np.sum(np.linalg.norm(pa[ok] - b.keypoints[best[ok]], axis=1) < tol)), int(ok.sum())


def test_descriptors_survive_a_scale_change(room_image):
    """Shrink the image to 60 %: a keypoint is described at its own pyramid level, so the
    descriptors of the shrunk image match the original's (describing every keypoint on the first
    octave, what OpenCV's compute() does with keypoints that carry no octave, matches fewer)."""
    ex = features.create("sift", max_keypoints=800)
    up = cv2.resize(room_image, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_CUBIC)
    s = 0.6
    small = cv2.resize(up, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    M = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5]])  # OpenCV pixel convention
    a, b = ex.extract(up), ex.extract(small)
    good, n = _correct_matches(a, b, M)
    assert good >= 50 and good / n > 0.8, (good, n)
    # the same keypoints described on the first octave only: fewer correct matches
    for f in (a, b):
        st = f.dense
        f.descriptors = ex._describe(st, st.xy, st.size, st.angle, np.zeros(len(st.xy), np.int64))
    good0, _ = _correct_matches(a, b, M)
    assert good > 1.05 * good0, (good, good0)  # measured: 275 (of 279) against 242


def test_a_sift_map_localizes(small_sequence, tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from conftest import localize_perturbed, small_build_config

    from favormap.build import build_map
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map

    m = build_map(small_sequence, small_build_config(extractor="sift", iterations=60, max_landmarks=300))
    path = tmp_path / "sift.h5"
    write_map(m, path)
    loc = Localizer(path)
    # the extractor's ratio test when matching without a prior (0.9 since 2026-11-26, was 0.8)
    assert loc.config.global_ratio == loc.extractor.policy.match_ratio == 0.9
    # and its cosine threshold (the paper's 0.7); one given explicitly is kept
    assert loc.config.match_threshold == loc.extractor.policy.match_threshold == 0.7
    assert Localizer(path, LocalizeConfig(match_threshold=0.55)).config.match_threshold == 0.55
    errs = localize_perturbed(loc, small_sequence.frames[1::5])
    assert np.median(errs[:, 0]) < 0.005 and np.median(errs[:, 1]) < 0.2, errs


def test_features_pickle_with_their_keypoint_frames(room_image):
    """Features travel to and from Ray workers by pickle: the keypoints' sizes, angles and octaves
    (read from OpenCV only when needed) arrive, and sampling gives the same descriptors."""
    import pickle

    ex = features.create("sift", max_keypoints=300)
    f = ex.extract(room_image)
    g = pickle.loads(pickle.dumps(f))
    for k in ("xy", "size", "angle", "octave"):
        assert np.array_equal(getattr(g.dense, k), getattr(f.dense, k))
    assert len(f.dense.size) == len(f.keypoints) and (f.dense.size > 0).all()
    pts = f.keypoints[:20] + 1.5
    assert np.array_equal(ex.sample(g, pts), ex.sample(f, pts))


def test_points_described_alike_are_described_once_with_the_same_result(room_image):
    """Points that OpenCV describes alike (the same position rounded in their octave's pixels, size,
    angle and octave) are described once: the result equals describing each point on its own."""
    from favormap.features.sift import _distinct

    ex = features.create("sift", max_keypoints=300)
    f = ex.extract(room_image)
    rng = np.random.default_rng(3)
    base = np.concatenate([f.keypoints[:20], rng.uniform(10, 230, (10, 2))]).astype(np.float32)
    pts = np.concatenate([base, base + 0.2, base, base + [1.0, 0.0]]).astype(np.float32)  # repeats, near-repeats
    alone = np.concatenate([ex.sample(f, pts[i : i + 1]) for i in range(len(pts))])
    np.testing.assert_array_equal(ex.sample(f, pts), alone)
    first, inverse = _distinct(
        pts - 0.5,
        np.full(len(pts), 12.0, np.float32),
        np.zeros(len(pts), np.float32),
        np.full(len(pts), 0x301, np.int64),
    )
    assert len(first) < 0.6 * len(pts) and np.array_equal(inverse[: len(base)], inverse[2 * len(base) : 3 * len(base)])
