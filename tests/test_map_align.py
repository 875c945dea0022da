"""Aligning two maps of one place (favormap.ops.align, favormap align, merge --align) on synthetic
scenes: disjoint halves of one sequence, the second built in another frame."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import SMALL, small_build_config

from favormap.geometry import camera_centers, rotvec_to_rotmat


def moved_sequence(seq, b_to_a):
    """``seq`` (frame a) with its poses expressed in frame b, where x_a = b_to_a x_b (a similarity)."""
    s = float(np.cbrt(np.linalg.det(b_to_a[:3, :3])))
    frames = []
    for f in seq.frames:
        cfw = f.cam_from_world @ b_to_a
        cfw[:3, :] /= s  # rigid again: camera coordinates in b's units
        frames.append(dataclasses.replace(f, cam_from_world=cfw))
    return dataclasses.replace(seq, frames=frames)


def random_similarity(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.exp(rng.uniform(-1, 1)) * rotvec_to_rotmat(rng.normal(size=3))
    T[:3, 3] = rng.normal(size=3) * 3
    return T


def transform_error(T_est, T_true, points_b) -> tuple[float, float]:
    """(largest distance between the points moved by both, rotation difference in degrees)."""
    pe = points_b @ T_est[:3, :3].T + T_est[:3, 3]
    pt = points_b @ T_true[:3, :3].T + T_true[:3, 3]
    Re = T_est[:3, :3] / np.cbrt(np.linalg.det(T_est[:3, :3]))
    Rt = T_true[:3, :3] / np.cbrt(np.linalg.det(T_true[:3, :3]))
    ang = np.degrees(np.arccos(np.clip((np.trace(Re @ Rt.T) - 1) / 2, -1, 1)))
    return float(np.max(np.linalg.norm(pe - pt, axis=1))), float(ang)


def _build(seq, path):
    from favormap.build import build_map
    from favormap.mapfile import write_map

    write_map(build_map(seq, small_build_config()), path)
    return path


@pytest.fixture(scope="module")
def halves(small_sequence, tmp_path_factory):
    """(a.h5, b.h5, b_to_a, sequence b): maps of the even and of the odd frames, b's poses moved by a
    random similarity."""
    root = tmp_path_factory.mktemp("align")
    n = len(small_sequence)
    T = random_similarity(np.random.default_rng(7))
    seq_b = moved_sequence(small_sequence.subset(range(1, n, 2)), T)
    a = _build(small_sequence.subset(range(0, n, 2)), root / "a.h5")
    b = _build(seq_b, root / "b.h5")
    return a, b, T, seq_b


@pytest.fixture(scope="module")
def other_scene(tmp_path_factory):
    """A map of another synthetic room (different layout and texture)."""
    from favormap.synthetic import write_sequence

    root = tmp_path_factory.mktemp("other")
    seq = write_sequence(root / "seq", **{**SMALL, "seed": 5, "n_frames": 8})
    return _build(seq, root / "other.h5")


def test_align_recovers_the_similarity_between_disjoint_halves(halves):
    from favormap.ops import align_maps

    a, b, T, seq_b = halves
    r = align_maps(a, b)
    centres_b = camera_centers(np.stack([f.cam_from_world for f in seq_b.frames]))
    centres_a = centres_b @ T[:3, :3].T + T[:3, 3]
    extent = float(np.linalg.norm(centres_a.max(0) - centres_a.min(0)))
    dt, dr = transform_error(r.b_to_a, T, centres_b)
    assert dt <= 0.005 * extent and dr <= 0.2, (dt / extent, dr, r.to_dict())
    assert r.num_inliers >= 12 and r.inlier_ratio >= 0.15
    assert r.rms < r.threshold
    # the bootstrap uncertainty is small and non-zero
    assert 0 < r.std_rotation_deg < 0.5 and 0 < r.std_log_scale < 0.01 and r.std_translation > 0


def test_align_refuses_maps_of_different_scenes(halves, other_scene):
    from favormap.ops import AlignmentError, align_maps

    with pytest.raises(AlignmentError, match="do not overlap enough"):
        align_maps(halves[0], other_scene)


def test_align_cli_writes_the_transform_merge_reads_and_refuses_in_one_line(halves, other_scene, tmp_path, capsys):
    from favormap.cli import main
    from favormap.io.posefile import read_transform

    a, b, T, _ = halves
    out = tmp_path / "b_to_a.txt"
    assert main(["align", str(a), str(b), "-o", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    T_file, s = read_transform(out)
    np.testing.assert_allclose(T_file, np.array(d["b_to_a"]), atol=1e-9)
    assert abs(s - np.cbrt(np.linalg.det(T[:3, :3]))) < 0.01 * s
    assert main(["align", str(a), str(other_scene), "-o", str(tmp_path / "bad.txt")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("favormap align: error: ") and "overlap" in err and "\n" not in err
    assert not (tmp_path / "bad.txt").exists()
    assert main(["align", str(a), str(tmp_path / "missing.h5")]) != 0
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_merge_align_gives_a_map_that_validates_in_a_frame(halves, tmp_path, capsys):
    from favormap.cli import main
    from favormap.mapfile import Map

    a, b, T, seq_b = halves
    out = tmp_path / "m.h5"
    assert main(["merge", str(a), str(b), "--align", "-o", str(out), "--json", "-q"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["alignment"]["num_inliers"] >= 12
    assert main(["validate", str(out)]) == 0
    capsys.readouterr()
    with Map.open(out) as m:
        cfw = np.asarray(m.cam_from_world)
    # b's frames are back in a's frame: their centres match the truth
    cb = camera_centers(np.stack([f.cam_from_world for f in seq_b.frames]))
    truth = cb @ T[:3, :3].T + T[:3, 3]
    got = camera_centers(cfw[-len(seq_b) :])
    extent = float(np.linalg.norm(truth.max(0) - truth.min(0)))
    assert np.max(np.linalg.norm(got - truth, axis=1)) <= 0.005 * extent
    assert main(["merge", str(a), str(b), "--align", "--transform", "x.txt", "-o", str(tmp_path / "n.h5")]) != 0
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
