"""The order tracking walks the frames in: as listed along a camera path, along a path through the
poses where the listing is none, and the same tracks either way."""

from __future__ import annotations

import numpy as np
import pytest
from test_tracking import CAM, _features

from favormap import frame_order
from favormap.geometry import look_at
from favormap.tracking import track_features

N_FRAMES = 24


def _walk(n=N_FRAMES, seed=0):
    """Cameras along a line past a wall of points 5 units away, each point in view of ~7 frames only."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(-6.0, 6.0, n)
    T = np.stack([look_at([x, 0.0, 0.0], [x, 0.0, 5.0], up=(0, -1, 0)) for x in xs])
    X = rng.uniform([-7.0, -1.0, 4.5], [7.0, 1.0, 5.5], size=(400, 3))
    visible = np.abs(xs[:, None] - X[None, :, 0]) < 1.6
    D = rng.normal(size=(len(X), 32)).astype(np.float32)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return X, T, D, visible, rng


def test_frames_listed_along_the_path_keep_their_order():
    _, T, *_ = _walk()
    assert np.array_equal(frame_order.matching_order(T), np.arange(len(T)))
    # a walk that pauses and turns is still a path
    turned = T.copy()
    turned[10:] = np.stack([look_at(-t[:3, :3].T @ t[:3, 3], [0.0, 0.0, 5.0], up=(0, -1, 0)) for t in T[10:]])
    assert np.array_equal(frame_order.matching_order(turned), np.arange(len(T)))


def test_shuffled_frames_are_walked_along_the_path_they_were_taken_on():
    _, T, *_ = _walk()
    perm = np.random.default_rng(3).permutation(len(T))
    order = frame_order.matching_order(T[perm])
    walked = perm[order]  # the frames' places along the line, in the order they are walked
    assert sorted(order) == list(range(len(T)))
    assert np.array_equal(walked, np.arange(len(T))) or np.array_equal(walked, np.arange(len(T))[::-1])


@pytest.mark.parametrize("n", [1, 2])
def test_one_or_two_frames_keep_their_order(n):
    _, T, *_ = _walk()
    assert np.array_equal(frame_order.matching_order(T[:n]), np.arange(n))


def _point_tracks(tracks, owners, frames):
    """Each track as (its point, the frames it was seen in, in the walk's own numbering)."""
    out = set()
    for a, b in zip(tracks.offsets[:-1], tracks.offsets[1:]):
        f, k = tracks.frame_idx[a:b], tracks.keypoint_idx[a:b]
        pts = {owners[i][j] for i, j in zip(f, k)}
        assert len(pts) == 1  # one point per track
        out.add((pts.pop(), tuple(sorted(frames[f]))))
    return out


def test_shuffled_frames_give_the_tracks_of_the_ordered_ones(monkeypatch):
    X, T, D, visible, rng = _walk()
    feats, owners = _features(X, T, D, rng, visible=visible)
    ordered = _point_tracks(track_features(feats, T, [CAM] * len(T), min_track=3, window=3), owners, np.arange(len(T)))
    perm = np.random.default_rng(5).permutation(len(T))

    def shuffled():
        args = [feats[i] for i in perm], T[perm], [CAM] * len(T)
        return _point_tracks(track_features(*args, min_track=3, window=3), [owners[i] for i in perm], perm)

    assert len(ordered) > 0.9 * len(X)
    assert shuffled() == ordered
    # walked in the order listed, the same shuffled frames meet their neighbours seldom
    monkeypatch.setattr("favormap.tracking.matching_order", lambda T: np.arange(len(T)))
    listed = shuffled()
    seen = sum(len(frames) for _, frames in listed)
    assert seen < 0.5 * sum(len(frames) for _, frames in ordered)
