"""At most LocalizeConfig.max_visible landmarks a localization step, spread over the image
(favormap.visibility.spread_rows)."""

from __future__ import annotations

import numpy as np
import pytest

from favormap.visibility import spread_rows


def test_every_cell_keeps_its_best_before_a_crowded_cell_gives_more():
    """100 rows in one corner of the image (high scores) and one row in each of 10 other cells (low
    scores), at most 20: every lone row is kept, then the corner's best 10 by score."""
    rng = np.random.default_rng(0)
    crowd = np.c_[rng.uniform(0, 30, 100), rng.uniform(0, 30, 100)]
    lone = np.c_[np.linspace(100, 620, 10), np.full(10, 400.0)]
    uv = np.r_[crowd, lone]
    score = np.r_[rng.uniform(0.5, 1.0, 100), np.full(10, 0.1)]
    rows = np.arange(1000, 1110)
    out = spread_rows(rows, uv, score, (640, 480), 20)
    assert len(out) == 20 and np.all(np.diff(out) > 0)
    assert set(rows[100:]) <= set(out)
    best_crowd = rows[np.argsort(-score[:100])[:10]]
    assert set(best_crowd) == set(out) - set(rows[100:])


def test_fewer_rows_than_asked_are_all_kept():
    rows = np.array([3, 7, 9])
    np.testing.assert_array_equal(spread_rows(rows, np.zeros((3, 2)), np.ones(3), (640, 480), 5), rows)


def test_a_capped_localizer_still_localizes(small_map, small_sequence):
    """The room's views see ~200-400 landmarks: capped at 150 a step, the pose stays within a centimetre
    and every step renders at most 150."""
    from favormap.geometry import perturb_pose, pose_error
    from favormap.localize import LocalizeConfig, Localizer

    _, path = small_map
    rng = np.random.default_rng(0)
    loc = Localizer(path, LocalizeConfig(max_visible=150))
    try:
        for k in (2, 8):
            f = small_sequence.frames[k]
            res = loc.localize(f.image_path, perturb_pose(f.cam_from_world, 0.1, 5.0, rng))
            assert res.success, res.message
            assert pose_error(res.cam_from_world, f.cam_from_world)[0] < 0.01
            assert max(it.num_visible for it in res.iterations if it.kind != "global") <= 150
    finally:
        loc.close()


def test_a_bad_cap_is_refused():
    from favormap.errors import InputError
    from favormap.localize import LocalizeConfig

    for bad in (0, -5, 2.5):
        with pytest.raises(InputError, match="max_visible"):
            LocalizeConfig(max_visible=bad)
