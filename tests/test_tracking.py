"""Tracking on its own (synthetic keypoints with known correspondences) and cheirality in
triangulation (points behind a camera)."""

from __future__ import annotations

import numpy as np
import pytest

from favormap.features import Features
from favormap.geometry import look_at, project
from favormap.io import Camera
from favormap.tracking import EPIPOLAR_CEILING, Tracks, epipolar_limit, track_features
from favormap.triangulation import TriangulationConfig, triangulate

CAM = Camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0])


def _rig(n_frames=8, n_points=120, seed=0):
    """Cameras on a line looking at a cloud of points 5 units away; a unit descriptor per point."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.5, -1.0, 4.0], [1.5, 1.0, 6.0], size=(n_points, 3))
    T = np.stack([look_at([x, 0.0, 0.0], [0.0, 0.0, 5.0], up=(0, -1, 0)) for x in np.linspace(-1, 1, n_frames)])
    D = rng.normal(size=(n_points, 32)).astype(np.float32)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return X, T, D, rng


def _features(X, T, D, rng, noise_px=0.2, visible=None, extra=None):
    """Per frame: the projections of the points visible in it (shuffled), descriptors with a
    little noise; ``extra[i]`` appends (xy, descriptor) rows. Returns features and, per frame, the
    point index of every keypoint (-1 for extra rows)."""
    feats, owners = [], []
    for i in range(len(T)):
        pts = np.flatnonzero(visible[i]) if visible is not None else np.arange(len(X))
        pts = rng.permutation(pts)
        xy = project(CAM.K, T[i], X[pts]) + rng.normal(0, noise_px, (len(pts), 2))
        d = D[pts] + rng.normal(0, 0.02, (len(pts), D.shape[1])).astype(np.float32)
        own = pts.copy()
        if extra is not None and i in extra:
            exy, ed = extra[i]
            xy, d, own = np.r_[xy, exy], np.r_[d, ed], np.r_[own, np.full(len(exy), -1)]
        d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
        feats.append(Features(xy.astype(np.float32), np.ones(len(xy), np.float32), d, (CAM.width, CAM.height)))
        owners.append(own)
    return feats, owners


def _owners_of(tracks: Tracks, owners) -> list[np.ndarray]:
    return [
        np.array([owners[f][k] for f, k in zip(tracks.frame_idx[a:b], tracks.keypoint_idx[a:b])])
        for a, b in zip(tracks.offsets[:-1], tracks.offsets[1:])
    ]


def test_tracks_join_the_keypoints_of_one_point_across_frames():
    X, T, D, rng = _rig()
    feats, owners = _features(X, T, D, rng)
    tracks = track_features(feats, T, [CAM] * len(T), min_track=5, window=3)
    assert len(tracks) >= 0.95 * len(X)
    per_track = _owners_of(tracks, owners)
    assert all(len(np.unique(o)) == 1 and o[0] >= 0 for o in per_track)  # one point per track
    assert len({int(o[0]) for o in per_track}) == len(tracks)  # one track per point
    assert np.all(tracks.lengths == len(T))  # seen everywhere, followed everywhere
    for a, b in zip(tracks.offsets[:-1], tracks.offsets[1:]):  # one observation per frame, in order
        assert np.all(np.diff(tracks.frame_idx[a:b]) > 0)
    # the keypoint pixels are carried unchanged
    f, k = tracks.frame_idx, tracks.keypoint_idx
    np.testing.assert_array_equal(tracks.xy, np.stack([feats[i].keypoints[j] for i, j in zip(f, k)]))


def test_tracking_drops_short_tracks_and_matches_that_break_the_epipolar_constraint():
    X, T, D, rng = _rig(n_points=60)
    visible = np.ones((len(T), len(X)), bool)
    visible[:, :10] = False
    visible[:3, :10] = True  # points 0..9 seen in 3 frames only: shorter than min_track
    # a decoy in frame 4: the descriptor of point 20 at a pixel far from its epipolar line
    decoy = (np.array([[50.0, 40.0]]), D[20:21])
    feats, owners = _features(X, T, D, rng, visible=visible, extra={4: decoy})
    tracks = track_features(feats, T, [CAM] * len(T), min_track=5, window=3, max_epipolar_px=2.0)
    per_track = _owners_of(tracks, owners)
    found = {int(o[0]) for o in per_track}
    assert not found & set(range(10))
    assert all(np.all(o >= 0) and len(np.unique(o)) == 1 for o in per_track)  # the decoy joined nothing
    assert found == set(range(10, 60))
    # without the pose check the decoy wins its mutual match (it is the exact descriptor)
    loose = track_features(feats, T, [CAM] * len(T), min_track=5, window=3, max_epipolar_px=1e9)
    assert any(np.any(o < 0) for o in _owners_of(loose, owners)) or len(loose) < len(tracks)
    # the run's match counts: the same mutual matches; the pose check refused the decoy's
    assert tracks.matches == loose.matches > 0 and loose.epipolar_matches == loose.matches
    assert 0 < tracks.epipolar_matches < tracks.matches and tracks.epipolar_matches <= tracks.epipolar_matches_3x


@pytest.mark.parametrize("sigma", [0.2, 0.8, 2.0])
def test_the_measured_epipolar_limit_follows_the_spread_of_the_right_matches(sigma):
    """Right matches' distances from their epipolar lines spread with the poses' error, wrong ones
    evenly: the measured limit rests on the right ones' median (3x it), whatever the share of wrong
    ones, within [floor, ceiling x floor]."""
    rng = np.random.default_rng(1)
    right = np.abs(rng.normal(0.0, sigma, (4000, 2))).sum(1) / 2  # a symmetric distance: two one-sided ones
    for wrong_share in (0.2, 0.5):
        n_wrong = int(len(right) * wrong_share / (1 - wrong_share))
        d = np.r_[right, rng.uniform(0, 300, n_wrong)]
        limit, median = epipolar_limit(d, floor=1.0)
        assert median == pytest.approx(np.median(right), rel=0.1, abs=0.06)
        assert limit == pytest.approx(float(np.clip(3 * median, 1.0, EPIPOLAR_CEILING)))
    assert epipolar_limit(right[:50], floor=1.5) == (1.5, pytest.approx(np.nan, nan_ok=True))  # too few: the floor


def test_tracking_measures_a_looser_limit_for_less_accurate_poses():
    """No limit given: exact poses keep the floor; poses moved by ~2 px get a limit that holds their
    right matches, and the tracks a fixed 1 px limit would break stay whole."""
    X, T, D, rng = _rig(n_points=300)
    feats, owners = _features(X, T, D, rng)
    exact = track_features(feats, T, [CAM] * len(T), min_track=5, window=3, max_epipolar_px=None)
    assert exact.max_epipolar_px == 1.0 and exact.epipolar_median_px < 0.5
    moved = T.copy()
    for i in range(len(T)):  # each camera turned by a random ~0.25 deg: ~2 px at f = 500
        axis = rng.normal(size=3)
        angle = np.deg2rad(0.25) * axis / np.linalg.norm(axis)
        K = np.array([[0, -angle[2], angle[1]], [angle[2], 0, -angle[0]], [-angle[1], angle[0], 0]])
        moved[i, :3, :3] = (np.eye(3) + K) @ T[i, :3, :3]
        u, _, vt = np.linalg.svd(moved[i, :3, :3])
        moved[i, :3, :3] = u @ vt
    fixed = track_features(feats, moved, [CAM] * len(T), min_track=5, window=3, max_epipolar_px=1.0)
    measured = track_features(feats, moved, [CAM] * len(T), min_track=5, window=3, max_epipolar_px=None)
    assert measured.max_epipolar_px > 2.0 and measured.epipolar_median_px > 0.7
    assert np.isnan(fixed.epipolar_median_px) and fixed.max_epipolar_px == 1.0
    assert measured.lengths.sum() > 1.3 * fixed.lengths.sum()
    assert all(len(np.unique(o)) == 1 and o[0] >= 0 for o in _owners_of(measured, owners))  # still right


def _two_keypoints_of_point_7():
    """30 points; point 7 has two keypoints in frame 2 (0.3 px apart, on its epipolar lines): one
    looks like point 7 in frames 0-1 (descriptor A), the other like point 7 in frames 3-7
    (descriptor B). Returns the poses, the features and each keypoint's point (-1: the second one)."""
    X, T, D, rng = _rig(n_points=30)
    a, b = (D[7] + 0.05 * rng.normal(size=D.shape[1]) for _ in range(2))
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    xy7 = project(CAM.K, T[2], X[7:8]) + np.array([[0.0, 0.3]])
    feats, owners = _features(X, T, D, rng, noise_px=0.0, extra={2: (xy7, b[None].astype(np.float32))})
    for i in range(len(T)):
        feats[i].descriptors[np.flatnonzero(owners[i] == 7)] = a if i <= 2 else b
    return T, feats, owners


def test_a_track_with_two_keypoints_in_one_frame_is_dropped():
    """Point 7 has two keypoints in frame 2 (0.3 px apart, on its epipolar lines): one looks like
    point 7 in frames 0-1 (descriptor A), the other like point 7 in frames 3-7 (descriptor B).
    Matching joins both into one component: ambiguous, so the whole track goes."""
    T, feats, owners = _two_keypoints_of_point_7()
    tracks = track_features(feats, T, [CAM] * len(T), min_track=5, window=3)
    found = {int(o[0]) for o in _owners_of(tracks, owners)}
    assert 7 not in found
    assert found == set(range(30)) - {7}
    # without the second keypoint, point 7 is tracked
    feats[2] = Features(feats[2].keypoints[:-1], feats[2].scores[:-1], feats[2].descriptors[:-1], feats[2].image_size)
    tracks = track_features(feats, T, [CAM] * len(T), min_track=5, window=3)
    assert 7 in {int(o[0]) for o in _owners_of(tracks, owners)}


def test_no_matches_give_no_tracks():
    X, T, D, rng = _rig(n_points=20)
    feats, _ = _features(X, T, D, rng)
    feats = [
        Features(f.keypoints, f.scores, np.roll(f.descriptors, i, axis=1), f.image_size) for i, f in enumerate(feats)
    ]
    tracks = track_features(feats, T, [CAM] * len(T), min_track=5, min_similarity=0.9)
    assert len(tracks) == 0 and len(tracks.frame_idx) == 0


# -- cheirality --------------------------------------------------------------------------------------
def _observe(X, T, noise_px=0.0, rng=None):
    """Tracks of every point in every camera, through the pinhole formula (also for cameras the
    point is behind: the pixel is where the formula puts it)."""
    fi = np.repeat(np.arange(len(T))[None], len(X), 0).ravel()
    tid = np.repeat(np.arange(len(X)), len(T))
    xy = np.stack([project(CAM.K, T[f], X[t : t + 1])[0] for f, t in zip(fi, tid)])
    if noise_px:
        xy += rng.normal(0, noise_px, xy.shape)
    return Tracks.from_obs(fi, np.arange(len(fi)), xy, tid)


def test_observations_from_behind_a_camera_are_dropped():
    """Six cameras see the points; two more face away from them, with the pixels the projection
    formula gives for points behind them (consistent in the image, impossible in 3D)."""
    X, T, _, rng = _rig(n_frames=6, n_points=40)
    away = np.stack([look_at([x, 0.0, 0.0], [x, 0.0, -5.0], up=(0, -1, 0)) for x in (-0.5, 0.5)])
    T_all = np.concatenate([T, away])
    depth_in_away = X @ away[:, 2, :3].T + away[:, 2, 3]
    assert np.all(depth_in_away < 0)  # the points really are behind the two cameras
    tracks = _observe(X, T_all, 0.2, rng)
    Ks = np.repeat(CAM.K[None], len(T_all), 0)
    lms = triangulate(tracks, T_all, Ks, TriangulationConfig(max_reproj_px=3.0, min_track=5))
    assert len(lms) == len(X)
    assert np.all(lms.tracks.frame_idx < len(T))  # no observation from behind survives
    assert np.all(lms.tracks.lengths == len(T))
    assert np.median(np.linalg.norm(lms.positions - X, axis=1)) < 0.01


@pytest.mark.parametrize("behind_all", [True, False])
def test_points_behind_the_cameras_give_no_landmark(behind_all):
    """Points mirrored behind the camera rig: their pixels are consistent (the projection formula
    cannot tell), but the point is behind every camera, so nothing is triangulated. With half the
    cameras turned around, each point is behind three of six cameras: too short a track remains."""
    X, T, _, _ = _rig(n_frames=6, n_points=30)
    X_behind = X * np.array([1.0, 1.0, -1.0])  # z in [-6, -4]: behind cameras at z = 0 looking +z
    if behind_all:
        T_use = T
    else:
        flip = np.diag([-1.0, 1.0, -1.0, 1.0])  # rotate 180 deg about the camera's y axis
        T_use = np.stack([flip @ t if i % 2 else t for i, t in enumerate(T)])
    tracks = _observe(X_behind, T_use)
    Ks = np.repeat(CAM.K[None], len(T_use), 0)
    lms = triangulate(tracks, T_use, Ks, TriangulationConfig(min_track=5))
    assert len(lms) == 0
    # the same tracks of points in front are triangulated (the rig is not degenerate)
    if behind_all:
        assert len(triangulate(_observe(X, T), T, Ks, TriangulationConfig(min_track=5))) == len(X)


def test_the_epipolar_distance_matrix_is_the_pairwise_distance():
    from favormap.tracking import epipolar_distance, epipolar_distance_matrix, fundamental

    X, T, D, rng = _rig(n_points=15)
    F = fundamental(T[0], CAM.K, T[3], CAM.K)
    xa = project(CAM.K, T[0], X) + rng.normal(0, 3.0, (len(X), 2))
    xb = project(CAM.K, T[3], X[:9]) + rng.normal(0, 3.0, (9, 2))
    M = epipolar_distance_matrix(F, xa, xb)
    ia, ib = np.meshgrid(np.arange(len(xa)), np.arange(len(xb)), indexing="ij")
    want = epipolar_distance(F, xa[ia.ravel()], xb[ib.ravel()]).reshape(M.shape)
    np.testing.assert_allclose(M, want, rtol=1e-5, atol=1e-4)
    assert np.all(np.diag(M[:9, :9]) < 20) and M.max() > 50  # true pairs near their lines, others not


def test_the_ratio_test_drops_matches_with_a_close_second_candidate():
    """Point 5 appears twice in frame 1 (its keypoint and a near-copy 40 px away): mutual nearest
    neighbours keep one of the two; with Lowe's ratio both ways the ambiguous match goes."""
    from favormap.tracking import mutual_nn

    X, T, D, rng = _rig(n_points=20)
    twin = D[5] + 0.01 * rng.normal(size=D.shape[1])
    feats, owners = _features(X, T[:2], D, rng, extra={1: (np.array([[40.0, 40.0]]), twin[None].astype(np.float32))})
    da, db = (f.descriptors for f in feats)
    ia, ib, s = mutual_nn(da, db, 0.7)
    assert 5 in owners[0][ia] and len(ia) == 20 and np.all(s >= 0.7)
    ja, jb, _ = mutual_nn(da, db, 0.7, ratio=0.8)
    assert 5 not in owners[0][ja]
    assert set(owners[0][ja]) == set(range(20)) - {5}
    assert np.all(owners[0][ja] == owners[1][jb])  # the others all kept, and right


def test_build_reports_the_share_of_matches_within_the_epipolar_limit(small_map, capsys):
    """A build records which shares of the mutual matches lie within the epipolar limit and within 3x
    it, and its summary says so; a given limit that many right matches seem to lie beyond (poses less
    accurate than it) gets a hint to let the build measure it."""
    from favormap.cli.build import print_summary

    m, _ = small_map
    st = m.provenance["stats"]
    # exact synthetic poses: nearly every match within 3x the limit lies within it
    assert 0 < st["epipolar_kept"] <= st["epipolar_kept_3x"] <= 1.0 and st["max_epipolar_px"] > 0
    assert st["epipolar_kept"] >= 0.6 * st["epipolar_kept_3x"]
    base = dict(
        frames=3, tracks=10, landmarks=5, triangulated=6, mean_track_length=3.0, median_reproj_error_px=0.5,
        median_psnr=30.0, median_cosine=0.9, file="m.h5", file_size=1000, timings={"track": 1.0},
        total_seconds=1.0, max_epipolar_px=1.0,
    )  # fmt: skip
    # the fox's (33 % / 39 %, its poses accurate) and with its rotations perturbed by 0.25 deg (13 % / 33 %)
    for kept, kept3, hint in ((0.33, 0.39, False), (0.13, 0.33, True)):
        print_summary({**base, "epipolar_kept": kept, "epipolar_kept_3x": kept3})
        out = capsys.readouterr().out
        assert f"within 1 px of their epipolar line: {round(100 * kept)} %, within 3 px: {round(100 * kept3)} %" in out
        assert ("leave --max-epipolar out to measure it" in out) == hint
        # a measured limit gives no hint, and says what it chose from
        print_summary({**base, "epipolar_kept": kept, "epipolar_kept_3x": kept3, "epipolar_measured": True,
                       "epipolar_median_px": 0.4})  # fmt: skip
        out = capsys.readouterr().out
        assert "--max-epipolar" not in out and "epipolar limit      1.00 px, measured" in out and "0.40 px" in out
    # the exact synthetic poses of the small map (its own statistics) suggest --exact-poses; the fox's
    # (85 % of the matches within 3 px within 1 px, 0.335 px) and a map built with it do not
    for stats, hint in (
        (st, True),
        ({"epipolar_kept": 0.33, "epipolar_kept_3x": 0.39, "median_reproj_error_px": 0.335}, False),
    ):
        print_summary({**base, **stats})
        assert ("--exact-poses localizes more precisely" in capsys.readouterr().out) == hint
    print_summary({**base, **st, "exact_poses": True})
    out = capsys.readouterr().out
    assert "localize aligns by default" in out and "--exact-poses" not in out
    # the landmark budget and how much of it two-view tracks fill
    assert st["max_landmarks"] == 400 and st["two_view_landmarks"] == int((np.asarray(m.track_length) == 2).sum())
    print_summary({**base, "max_landmarks": 3000, "two_view_landmarks": 2})
    assert "landmarks           5  (triangulated 6; budget 3000, 2 of two views)" in capsys.readouterr().out
    print_summary(
        {**base, "max_landmarks": 3000, "min_frame_landmarks": 300, "coverage_landmarks": 4, "two_view_landmarks": 2}
    )
    out = capsys.readouterr().out
    assert "(triangulated 6; budget 3000 + 4 for frames that saw fewer than 300, 2 of two views)" in out


def test_tracking_on_a_pool_of_threads_gives_the_serial_tracks():
    """With more than one worker, a frame's pairs are matched on a pool of threads (one BLAS thread
    each): the tracks and match counts are those of the serial run."""
    X, T, D, rng = _rig(n_frames=10, n_points=300)
    feats, _ = _features(X, T, D, rng, noise_px=0.6)
    got = {n: track_features(feats, T, [CAM] * len(T), min_track=3, window=4, workers=n) for n in (1, 2, 3)}
    a = got[1]
    assert len(a) > 200
    for b in (got[2], got[3]):
        for k in ("frame_idx", "keypoint_idx", "xy", "offsets"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        assert (a.matches, a.epipolar_matches, a.epipolar_matches_3x) == (
            b.matches,
            b.epipolar_matches,
            b.epipolar_matches_3x,
        )


def test_connected_components_number_components_as_scipy_does():
    """The union-find in NumPy gives scipy's labels (components numbered by their smallest node) on
    random graphs, long chains and isolated nodes."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    from favormap.tracking import connected_components

    rng = np.random.default_rng(3)
    for trial in range(60):
        n = int(rng.integers(1, 300))
        e = int(rng.integers(0, 2 * n))
        a, b = rng.integers(0, n, e), rng.integers(0, n, e)
        if trial % 3 == 0:  # one long chain in random order
            p = rng.permutation(n)
            a, b = np.r_[a, p[:-1]], np.r_[b, p[1:]]
        want = scipy_components(coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n)), directed=False)[1]
        np.testing.assert_array_equal(connected_components(n, a, b), want)
    assert connected_components(0, [], []).shape == (0,)


def test_two_view_tracks_fill_only_the_budget_that_longer_tracks_leave():
    """With the default shortest track (two frames), points seen in two frames become landmarks; the
    selection keeps every longer track before any two-view one, so a budget that the longer tracks fill
    holds no two-view landmark, and a larger one takes the two-view landmarks after all the longer ones."""
    from favormap.build import select_landmarks
    from favormap.build_config import BuildConfig

    assert BuildConfig().min_track == 2
    X, T, D, rng = _rig(n_points=90)
    visible = np.ones((len(T), len(X)), bool)
    visible[:, :30] = False
    visible[2:4, :30] = True  # points 0..29 seen in frames 2 and 3 only
    feats, owners = _features(X, T, D, rng, visible=visible)
    tracks = track_features(feats, T, [CAM] * len(T), min_track=BuildConfig().min_track, window=3)
    lms = triangulate(tracks, T, np.stack([CAM.K] * len(T)), TriangulationConfig(min_track=2))
    lengths = lms.tracks.lengths
    two = {int(o[0]) for o, n in zip(_owners_of(lms.tracks, owners), lengths) if n == 2}
    assert two == set(range(30))  # every two-view point triangulated, and only those are two-view tracks
    n_long = int((lengths > 2).sum())
    assert n_long == 60
    full = select_landmarks(lms, n_long)
    assert len(full) == n_long and full.tracks.lengths.min() > 2
    more = select_landmarks(lms, n_long + 10)
    assert (more.tracks.lengths == 2).sum() == 10 and (more.tracks.lengths > 2).sum() == n_long


def test_frames_that_see_too_few_landmarks_keep_their_best_tracks_beyond_the_budget():
    """The budget goes to the longest tracks; a frame that then sees fewer than min_frame_landmarks of
    them gets its best remaining tracks (longer first) up to that count, where its tracks allow."""
    from favormap.build import select_landmarks
    from favormap.build_config import BuildConfig

    assert BuildConfig().min_frame_landmarks == 300 and BuildConfig(max_landmarks=400).min_frame_landmarks == 40
    X, T, D, rng = _rig(n_points=100)
    visible = np.zeros((len(T), len(X)), bool)
    visible[0:6, 0:50] = True  # six-view tracks, in frames 0-5
    visible[5:8, 50:80] = True  # three-view tracks, in frames 5-7
    visible[6:8, 80:100] = True  # two-view tracks, in frames 6-7
    feats, owners = _features(X, T, D, rng, visible=visible)
    tracks = track_features(feats, T, [CAM] * len(T), min_track=2, window=3)
    lms = triangulate(tracks, T, np.stack([CAM.K] * len(T)), TriangulationConfig(min_track=2))
    assert len(lms) == 100

    def seen(sel):
        return np.bincount(sel.tracks.frame_idx, minlength=len(T))

    def points(sel):
        return {int(o[0]) for o in _owners_of(sel.tracks, owners)}

    budget_only = select_landmarks(lms, 50, 0)
    assert points(budget_only) == set(range(50)) and seen(budget_only)[6:].tolist() == [0, 0]
    covered = select_landmarks(lms, 50, 40)
    assert seen(covered)[6:].tolist() == [40, 40]  # frames 6 and 7 reach 40: the 30 three-view tracks first
    assert points(covered) >= set(range(80)) and len(points(covered) & set(range(80, 100))) == 10
    kept_two = [e for e, n in zip(covered.mean_reproj_error, covered.tracks.lengths) if n == 2]
    rest = [e for e, n in zip(lms.mean_reproj_error, lms.tracks.lengths) if n == 2]
    assert max(kept_two) <= sorted(rest)[9] + 1e-12  # the two-view tracks of lowest error
    assert (np.diff(covered.tracks.lengths) <= 0).all()  # best first, as the budget orders them
    # a frame's tracks bound what it can reach; frames already above the count gain nothing
    everything = select_landmarks(lms, 50, 1000)
    assert len(everything) == 100 and seen(everything)[:5].tolist() == [50] * 5


def test_the_reprojection_figure_counts_landmarks_of_three_or_more_views(small_map):
    """A two-view landmark fits its two rays up to their epipolar residual alone: the map's reprojection
    figure (build summary, info, the --exact-poses hint) is the median over landmarks of 3 or more
    observations, over all of them only when there are none such."""
    from favormap.mapfile.model import median_landmark_reproj_error

    e = np.array([0.05, 0.05, 0.05, 0.4, 0.5, 0.6], np.float32)
    n = np.array([2, 2, 2, 3, 4, 5])
    assert median_landmark_reproj_error(e, n) == pytest.approx(0.5)
    assert median_landmark_reproj_error(e, np.full(6, 2)) == pytest.approx(0.225)
    assert median_landmark_reproj_error(e) == pytest.approx(0.225)
    assert median_landmark_reproj_error(np.zeros(0), np.zeros(0)) is None
    from favormap.mapfile import Map

    m, path = small_map
    e, n = np.asarray(m.reproj_error), np.asarray(m.track_length)
    expected = float(np.median(e[n >= 3]))
    assert m.provenance["stats"]["median_reproj_error_px"] == pytest.approx(expected)
    with Map.open(path) as mm:
        assert mm.info()["median_reproj_error_px"] == pytest.approx(expected)
