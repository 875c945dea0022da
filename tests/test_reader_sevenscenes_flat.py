"""The flat 7-Scenes layout (tsdf-fusion): detection, camera-intrinsics.txt, the focal policy.

Every input is synthesised in tmp_path in that layout (tiny noise images, numpy-saved poses)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from favormap.errors import SequenceError
from favormap.geometry import inverse, look_at
from favormap.io import detect_format, read_sequence
from favormap.io.readers import sevenscenes_flat

W, H = 64, 48


def _write_flat(root: Path, n: int = 3, K: np.ndarray | None = None, ext: str = "jpg") -> list[np.ndarray]:
    """n frames ``frame-NNNNNN.color.EXT`` + ``.pose.txt`` (camera-to-world, space separated as numpy
    saves it) and a ``camera-intrinsics.txt``; returns the cam_from_world poses."""
    rng = np.random.default_rng(0)
    poses = []
    for i in range(n):
        a = 0.2 * i
        T = look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
        stem = root / f"frame-{5 * i:06d}"
        assert cv2.imwrite(f"{stem}.color.{ext}", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        np.savetxt(f"{stem}.pose.txt", inverse(T))
        poses.append(T)
    if K is None:
        K = np.array([[58.5, 0, 32], [0, 58.5, 24], [0, 0, 1]])  # the published 585 / 320 / 240, scaled
    np.savetxt(root / "camera-intrinsics.txt", K)
    return poses


def test_flat_folder_detected_with_its_intrinsics(tmp_path, caplog):
    poses = _write_flat(tmp_path)
    assert detect_format(tmp_path) == "7scenes-flat"
    with caplog.at_level(logging.INFO, logger="favormap"):
        seq = read_sequence(tmp_path)
    assert seq.format == "7scenes-flat" and len(seq) == 3
    assert [f.name for f in seq.frames] == [f"frame-{5 * i:06d}.color.jpg" for i in range(3)]
    for f, T in zip(seq.frames, poses):
        np.testing.assert_allclose(f.cam_from_world, T, atol=1e-12)
    cam = seq.cameras[0]
    assert cam.model == "PINHOLE" and (cam.width, cam.height) == (W, H)
    # the default policy replaces the published depth focal by the RGB camera's, and says so in one line
    assert sevenscenes_flat.FOCAL_POLICY == "rgb"
    expected = 52.5
    np.testing.assert_allclose(cam.params, [expected, expected, 32, 24])
    assert seq.extra["focal"]["fx"] == pytest.approx(expected)
    lines = [r.getMessage() for r in caplog.records if "focal" in r.getMessage()]
    assert len(lines) == 1 and f"{expected:g}" in lines[0]


def test_rgb_policy_replaces_only_the_depth_focal(tmp_path):
    _write_flat(tmp_path)
    rgb = sevenscenes_flat.read_with_focal(tmp_path, "rgb")
    np.testing.assert_allclose(rgb.cameras[0].params, [52.5, 52.5, 32, 24])  # 525 px scaled to 64 px wide
    assert "depth" in rgb.extra["focal"]["source"]
    as_file = sevenscenes_flat.read_with_focal(tmp_path, "file")
    np.testing.assert_allclose(as_file.cameras[0].params, [58.5, 58.5, 32, 24])
    # a K that is not the published depth value is taken as given under either policy
    for f in tmp_path.glob("*"):
        f.unlink()
    _write_flat(tmp_path, K=np.array([[60.0, 0, 31.5], [0, 61.0, 23.5], [0, 0, 1]]), ext="png")
    other = sevenscenes_flat.read_with_focal(tmp_path, "rgb")
    np.testing.assert_allclose(other.cameras[0].params, [60.0, 61.0, 31.5, 23.5])


def test_without_intrinsics_file_the_7scenes_reader_reads_it(tmp_path):
    _write_flat(tmp_path)
    (tmp_path / "camera-intrinsics.txt").unlink()
    assert detect_format(tmp_path) == "7scenes"


@pytest.mark.parametrize("case", ["bad_K", "missing_pose", "policy"])
def test_flat_folder_errors(tmp_path, case):
    _write_flat(tmp_path)
    if case == "bad_K":
        (tmp_path / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
        with pytest.raises(SequenceError, match="9 numbers"):
            read_sequence(tmp_path)
    elif case == "missing_pose":
        (tmp_path / "frame-000005.pose.txt").unlink()
        with pytest.raises(SequenceError, match="missing pose file"):
            read_sequence(tmp_path)
    else:
        with pytest.raises(ValueError, match="focal policy"):
            sevenscenes_flat.read_with_focal(tmp_path, "depth")
