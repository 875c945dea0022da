"""Pose, transform and camera files: both pose formats, round trips, and clear errors on bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from favormap.errors import InputError
from favormap.geometry import inverse, look_at, rotmat_to_quat
from favormap.io.posefile import format_pose_tum, read_camera, read_pose, read_transform, write_pose


@pytest.fixture
def pose():
    return look_at([1.0, -2.0, 1.5], [0.2, 0.5, 0.8], up=(0, 0, 1))  # cam_from_world


def test_matrix_pose_roundtrip(tmp_path, pose):
    p = write_pose(tmp_path / "pose.txt", pose)
    np.testing.assert_allclose(np.loadtxt(p), inverse(pose), atol=1e-12)  # the file holds world_from_cam
    np.testing.assert_allclose(read_pose(p), pose, atol=1e-10)


def test_sevenscenes_style_matrix_with_tabs_and_rounding(tmp_path, pose):
    wfc = inverse(pose)
    text = "\n".join("\t".join(f"{v:.7e}" for v in row) + "\t" for row in wfc) + "\n"
    (tmp_path / "frame-000000.pose.txt").write_text(text)
    got = read_pose(tmp_path / "frame-000000.pose.txt")
    np.testing.assert_allclose(got, pose, atol=1e-6)
    R = got[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)  # cleaned up to an exact rotation


def test_3x4_matrix_and_comments(tmp_path, pose):
    wfc = inverse(pose)
    (tmp_path / "p.txt").write_text(
        "# world_from_cam\n" + "\n".join(" ".join(repr(float(v)) for v in r) for r in wfc[:3]) + "  # 3x4\n"
    )
    np.testing.assert_allclose(read_pose(tmp_path / "p.txt"), pose, atol=1e-10)


def test_tum_line_with_and_without_timestamp(tmp_path, pose):
    wfc = inverse(pose)
    q = rotmat_to_quat(wfc[:3, :3])
    (tmp_path / "a.txt").write_text(" ".join(map(str, [*wfc[:3, 3], *q])) + "\n")
    np.testing.assert_allclose(read_pose(tmp_path / "a.txt"), pose, atol=1e-10)
    (tmp_path / "b.txt").write_text("1305031102.175304 " + " ".join(map(str, [*wfc[:3, 3], *q])))
    np.testing.assert_allclose(read_pose(tmp_path / "b.txt"), pose, atol=1e-10)
    (tmp_path / "c.txt").write_text(format_pose_tum(pose))
    np.testing.assert_allclose(read_pose(tmp_path / "c.txt"), pose, atol=1e-7)


@pytest.mark.parametrize(
    "content,needle",
    [
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "found 12"),  # would be fine... replaced below
        ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not a rotation"),  # scaled
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", "not a rotation"),  # reflection
        ("1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n", "non-finite"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 inf\n0 0 0 1\n", "non-finite"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0\n", "found 15"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n1 0 0 1\n", "last row"),
        ("1 2 3 0 0 0 2\n", "unit quaternion"),
        ("1 2 3\n0 0 0 1\n", "found 7 number(s) on 2 line(s)"),
        ("", "found 0"),
        ("1 0 0 0 x\n", "not a number"),
    ],
)
def test_bad_pose_files_name_the_file(tmp_path, content, needle):
    if needle == "found 12":  # a valid 3x4 file: check it parses
        (tmp_path / "ok.txt").write_text(content)
        np.testing.assert_allclose(read_pose(tmp_path / "ok.txt"), np.eye(4))
        return
    f = tmp_path / "bad_pose.txt"
    f.write_text(content)
    with pytest.raises(InputError) as e:
        read_pose(f)
    assert "bad_pose.txt" in str(e.value) and needle in str(e.value)
    assert "\n" not in str(e.value)


def test_missing_pose_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_pose(tmp_path / "nope.txt")
    with pytest.raises(InputError, match="directory"):
        read_pose(tmp_path)


def test_write_pose_refuses_non_rigid(tmp_path):
    with pytest.raises(InputError):
        write_pose(tmp_path / "x.txt", np.diag([2.0, 1, 1, 1]))


def test_transform_files(tmp_path):
    from favormap.geometry import rotation_about

    T = np.eye(4)
    T[:3, :3] = rotation_about([0, 0, 1], 0.3)
    T[:3, 3] = [1, 2, 3]
    np.savetxt(tmp_path / "t.txt", T)
    got, s = read_transform(tmp_path / "t.txt")
    np.testing.assert_allclose(got, T, atol=1e-12)
    assert s == pytest.approx(1.0)
    S = T.copy()
    S[:3, :3] *= 2.5
    np.savetxt(tmp_path / "s.txt", S)
    got, s = read_transform(tmp_path / "s.txt")
    assert s == pytest.approx(2.5) and np.allclose(got, S)
    with pytest.raises(InputError, match="scales"):
        read_transform(tmp_path / "s.txt", allow_scale=False)
    bad = T.copy()
    bad[0, 1] += 0.5  # shear
    np.savetxt(tmp_path / "shear.txt", bad)
    with pytest.raises(InputError, match="shear.txt"):
        read_transform(tmp_path / "shear.txt")
    np.savetxt(tmp_path / "mirror.txt", np.diag([1.0, 1, -1, 1]))
    with pytest.raises(InputError, match="determinant"):
        read_transform(tmp_path / "mirror.txt")
    (tmp_path / "short.txt").write_text("1 0 0 0 1 0 0")
    with pytest.raises(InputError, match="4x4"):
        read_transform(tmp_path / "short.txt")


def test_camera_specs(tmp_path):
    c = read_camera("1 PINHOLE 640 480 500 510 320 240")
    assert (c.model, c.width, c.height) == ("PINHOLE", 640, 480)
    np.testing.assert_allclose(c.params, [500, 510, 320, 240])
    c = read_camera("SIMPLE_RADIAL 320 240 250 160 120 0.01")
    assert c.model == "SIMPLE_RADIAL" and c.width == 320 and c.params[-1] == 0.01
    js = {"model": "OPENCV", "width": 100, "height": 80, "params": [90, 91, 50, 40, 0.1, 0.01, 0, 0]}
    c = read_camera(json.dumps(js))
    assert c.model == "OPENCV" and c.height == 80 and len(c.params) == 8
    (tmp_path / "cam.json").write_text(json.dumps(js))
    assert read_camera(str(tmp_path / "cam.json")).width == 100
    (tmp_path / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "# Number of cameras: 1\n3 SIMPLE_PINHOLE 64 48 50 32 24\n"
    )
    c = read_camera(str(tmp_path / "cameras.txt"))
    assert c.model == "SIMPLE_PINHOLE" and c.width == 64
    for bad, needle in [
        ("FISHEYE 64 48 1 2 3", "unsupported"),
        ("PINHOLE 64 48 1 2 3", "needs 4"),
        ("PINHOLE 64.5 48 1 2 3 4", "integers"),
        ('{"model": "PINHOLE"}', "keys"),
        ("{not json", "invalid JSON"),
        (str(tmp_path / "missing.txt"), "not found"),
    ]:
        with pytest.raises(InputError, match=needle):
            read_camera(bad)
