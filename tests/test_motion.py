"""Priors for a stream of query frames (favormap.localize.motion) and sequential localization."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from favormap.errors import InputError
from favormap.geometry import look_at, pose_error
from favormap.localize import MotionPrior


def _path(n=6):
    """cam_from_world of a camera that moves by one fixed motion per frame (0.1 units forward and
    sideways, turning 2 degrees: a steady screw motion in its own frame)."""
    from favormap.geometry import rotvec_to_rotmat

    step = np.eye(4)
    step[:3, :3] = rotvec_to_rotmat(np.radians([0.0, 2.0, 0.5]))
    step[:3, 3] = (0.1, 0.0, -0.1)
    out = [look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], up=(0, -1, 0))]
    for _ in range(n - 1):
        out.append(step @ out[-1])
    return out


def _ok(T):
    return SimpleNamespace(success=True, cam_from_world=T)


def _failed(T):
    return SimpleNamespace(success=False, cam_from_world=T)


def test_the_first_prior_is_the_given_one_or_none():
    T = _path()
    assert MotionPrior().prior() is None
    np.testing.assert_allclose(MotionPrior(first=T[0]).prior(), T[0])
    with pytest.raises(InputError, match="unknown motion model"):
        MotionPrior("teleport")


def test_constant_velocity_predicts_a_steady_motion_and_previous_holds_the_last_pose():
    T = _path()
    cv, prev = MotionPrior("constant-velocity"), MotionPrior("previous")
    for k in range(3):
        cv.update(_ok(T[k]))
        prev.update(_ok(T[k]))
    # the camera moves and turns at a constant rate: the next pose is predicted exactly
    dt, dr = pose_error(cv.prior(), T[3])
    assert dt < 1e-9 and dr < 1e-6
    np.testing.assert_allclose(prev.prior(), T[2])
    assert pose_error(prev.prior(), T[3])[0] > 0.09


def test_a_failed_frame_keeps_the_last_localized_pose_and_breaks_the_velocity():
    T = _path()
    mp = MotionPrior("constant-velocity")
    mp.update(_ok(T[0]))
    mp.update(_ok(T[1]))
    far = T[4].copy()
    far[:3, 3] += 100.0
    mp.update(_failed(far))  # frame 2 failed: its (wrong) pose is not used
    np.testing.assert_allclose(mp.prior(), T[1])  # frame 3: frames 1 and 3 are not consecutive
    mp.update(_ok(T[3]))
    np.testing.assert_allclose(mp.prior(), T[3])  # frames 1 and 3 are two apart: no velocity yet
    mp.update(_ok(T[4]))
    assert pose_error(mp.prior(), T[5])[0] < 1e-9  # 3 and 4 consecutive: velocity again


def test_localize_sequence_needs_the_global_search_only_for_the_first_frame(small_map, small_sequence):
    from favormap.localize import Localizer

    _, path = small_map
    frames = small_sequence.frames[3:9]
    loc = Localizer(str(path))
    try:
        results = list(loc.localize_sequence([f.image_path for f in frames]))
    finally:
        loc.close()
    assert all(r.success for r in results), [r.message for r in results]
    for r, f in zip(results, frames):
        assert pose_error(r.cam_from_world, f.cam_from_world)[0] < 0.01
    assert results[0].iterations[0].kind == "global"  # no prior for the first frame
    assert results[0].prior is None and all(r.prior is not None for r in results[1:])  # the priors used
    assert all(it.kind != "global" for r in results[1:] for it in r.iterations)


def test_cli_localizes_a_folder_as_a_sequence(small_map, small_sequence, tmp_path, capsys):
    import shutil

    from favormap.cli import main

    _, path = small_map
    folder = tmp_path / "stream"
    folder.mkdir()
    frames = small_sequence.frames[2:8]
    for k, fr in enumerate(frames):
        shutil.copy(fr.image_path, folder / f"{k:03d}{fr.image_path.suffix}")
    for extra in ([], ["--fixed-landmarks", "--motion", "previous"]):
        assert main(["localize", str(path), str(folder), "--sequential", "--json", *extra]) == 0
        rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert len(rows) == len(frames) and all(r["success"] for r in rows)
        kinds = [[it["kind"] for it in r["iterations"]] for r in rows]
        assert "global" in kinds[0] and not any("global" in k for k in kinds[1:]), kinds


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--sequential", "--priors", "p.txt"], "--sequential takes its priors"),
        (["--prior", "p.txt"], "--prior is for one image"),
        (["--fixed-landmarks"], "go with --sequential"),
        (["--motion", "previous"], "go with --sequential"),
    ],
)
def test_cli_sequential_option_errors(small_map, small_sequence, tmp_path, capsys, extra, message):
    from favormap.cli import main

    _, path = small_map
    folder = tmp_path / "q"
    folder.mkdir()
    (tmp_path / "p.txt").write_text("x 0 0 0 0 0 0 1\n")
    args = [a if a != "p.txt" else str(tmp_path / "p.txt") for a in extra]
    assert main(["localize", str(path), str(folder), *args]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_cli_sequential_needs_a_folder(small_map, small_sequence, capsys):
    from favormap.cli import main

    _, path = small_map
    assert main(["localize", str(path), str(small_sequence.frames[0].image_path), "--sequential"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--sequential localizes a folder" in err[0], err
