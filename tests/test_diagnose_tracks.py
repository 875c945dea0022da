"""tools/diagnose_tracks.py's count of a baseline point's observations against favormap's tracks, on
tracks and keypoints laid out by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import diagnose_tracks as diag  # noqa: E402


def _frames(n, extra):
    """Per frame, a few unrelated keypoints plus ``extra[f]`` where given."""
    base = np.array([[500.0, 400.0], [20.0, 30.0]])
    return [np.vstack([base, extra[f]]) if f in extra else base for f in range(n)]


def test_each_observation_of_a_point_is_counted_by_where_favormap_has_it():
    # the baseline point: seen at (100, 100) in frames 0..5 and 20
    frame = np.array([0, 1, 2, 3, 4, 5, 20])
    point = np.zeros(len(frame), int)
    xy = np.tile([100.0, 100.0], (len(frame), 1))
    # favormap: landmark 7 holds frames 0, 1, 2 (0.3 px off); landmark 9 holds frame 3
    tracks = (
        np.array([7, 7, 7, 9, 9]),
        np.array([0, 1, 2, 3, 11]),
        np.array([[100.3, 100.0], [100.0, 100.3], [99.8, 100.1], [100.0, 100.0], [300.0, 300.0]]),
    )
    near = np.array([[100.4, 99.8]])
    detected = _frames(21, {4: near, 20: near})  # frame 4: within the window of frame 2; 20: beyond it
    everywhere = _frames(21, {4: near, 20: near, 5: near})  # frame 5: only without the keypoint cap
    points, counts = diag.count_observations(point, frame, xy, tracks, detected, everywhere, window=10)
    assert points == 1
    assert counts == {
        "in track": 3,
        "other landmark": 1,
        "not tracked": 1,
        "beyond the window": 1,
        "beyond the cap": 1,
    }
    # farther than the radius nothing is the same feature: the point meets no landmark
    points, counts = diag.count_observations(point, frame, xy + 5.0, tracks, detected, everywhere, window=10)
    assert points == 0 and not counts


def test_short_points_are_left_out_and_an_undetected_observation_is_counted():
    frame = np.array([0, 1, 0, 1, 2])
    point = np.array([0, 0, 1, 1, 1])  # point 0: two observations; point 1: three
    xy = np.array([[10.0, 10.0], [10.0, 10.0], [50.0, 50.0], [50.0, 50.0], [50.0, 50.0]])
    tracks = (np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), xy[:4].copy())
    none = [np.zeros((0, 2))] * 3
    points, counts = diag.count_observations(point, frame, xy, tracks, none, none, window=10, min_length=3)
    assert points == 1
    assert counts == {"in track": 2, "not detected": 1}
