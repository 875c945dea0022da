"""Within one query a landmark keeps its descriptor while the camera sees it along nearly the same ray
(favormap.localize.descriptors.SeenRays, LocalizeConfig.rerender_angle_deg)."""

from __future__ import annotations

import numpy as np
import pytest

from favormap.geometry import look_at


class CountingSource:
    """A view-dependent source: each descriptor encodes the direction from the camera centre to the
    landmark; it counts the landmarks it was asked for."""

    name = "counting"
    one_per_landmark = True

    def __init__(self, positions):
        self.positions, self.asked = positions, []

    def __call__(self, rows, cam_from_world, timings):
        self.asked.append(np.array(rows))
        c = -cam_from_world[:3, :3].T @ cam_from_world[:3, 3]
        d = self.positions[rows] - c
        out = np.zeros((len(rows), 8), np.float32)
        out[:, :3] = d / np.linalg.norm(d, axis=1, keepdims=True)
        return out


def _pose(eye):
    return look_at(np.asarray(eye, float), np.zeros(3))


def test_a_landmark_seen_along_nearly_the_same_ray_keeps_its_descriptor():
    from favormap.localize.descriptors import SeenRays, describe

    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (50, 3))
    src = CountingSource(X)
    seen = SeenRays(X, 1.0)
    rows = np.arange(0, 50, 2)
    first, drows = describe(src, rows, _pose([0, 0, -5]), {}, seen)
    np.testing.assert_array_equal(drows, rows)
    np.testing.assert_allclose(first, src(rows, _pose([0, 0, -5]), {}))
    src.asked.clear()
    # 2 mm away: every ray within 1 deg, nothing rendered again; new landmarks are
    again, _ = describe(src, np.arange(50), _pose([0.002, 0, -5]), {}, seen)
    np.testing.assert_array_equal(src.asked[0], np.arange(1, 50, 2))
    np.testing.assert_array_equal(again[::2], first)
    # 1 m away: every ray turned by more than 1 deg, everything rendered again from there
    src.asked.clear()
    far, _ = describe(src, rows, _pose([1.0, 0, -5]), {}, seen)
    np.testing.assert_array_equal(src.asked[0], rows)
    np.testing.assert_allclose(far, src(rows, _pose([1.0, 0, -5]), {}))
    # 2 mm from there: the even rows keep what they got from there, the odd ones are turned and rendered again
    src.asked.clear()
    both, _ = describe(src, np.arange(50), _pose([1.002, 0, -5]), {}, seen)
    np.testing.assert_array_equal(src.asked[0], np.arange(1, 50, 2))
    np.testing.assert_array_equal(both[::2], far)


def test_seen_rays_keep_every_landmark_as_their_store_grows():
    """Thousands of landmarks stored in several steps (the store grows), some described again: each landmark
    keeps its latest descriptor."""
    from favormap.localize.descriptors import SeenRays, describe

    X = np.random.default_rng(2).uniform(-1, 1, (5000, 3))
    src = CountingSource(X)
    seen = SeenRays(X, 1.0)
    pose = _pose([0, 0, -5])
    for rows in (np.arange(0, 5000, 3), np.arange(0, 5000, 2), np.arange(5000)):
        got, _ = describe(src, rows, pose, {}, seen)
        np.testing.assert_allclose(got, src(rows, pose, {}))
    src.asked.clear()
    describe(src, np.arange(5000), pose, {}, seen)
    assert len(src.asked[0]) == 0  # all kept


def test_without_seen_rays_every_call_renders():
    from favormap.localize.descriptors import describe

    X = np.random.default_rng(1).uniform(-1, 1, (10, 3))
    src = CountingSource(X)
    for _ in range(2):
        describe(src, np.arange(10), _pose([0, 0, -5]), {})
    assert [len(a) for a in src.asked] == [10, 10]


def test_a_bad_rerender_angle_is_refused():
    from favormap.errors import InputError
    from favormap.localize import LocalizeConfig

    for bad in (-1, 200, "one"):
        with pytest.raises(InputError, match="rerender_angle_deg"):
            LocalizeConfig(rerender_angle_deg=bad)
