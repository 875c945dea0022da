"""`favormap pose`: priors from the poses other tools write."""

from __future__ import annotations

import json

import numpy as np
import pytest

from favormap.cli import main
from favormap.errors import InputError
from favormap.geometry import inverse, look_at, rotmat_to_quat, world_from_cam_opencv_to_opengl
from favormap.io.posefile import convert_pose, read_pose

T = look_at((1.0, -2.0, 0.5), (0.2, 0.1, 0.0), up=(0.0, 0.0, 1.0))  # cam_from_world
WFC = inverse(T)


def _mat(M) -> str:
    return "\n".join(" ".join(f"{v:.12g}" for v in row) for row in M) + "\n"


def _sources(tmp_path) -> dict:
    qx, qy, qz, qw = rotmat_to_quat(T[:3, :3])  # COLMAP: cam_from_world, QW first
    tx, ty, tz = T[:3, 3]
    wq = rotmat_to_quat(WFC[:3, :3])  # TUM: world_from_cam, qx qy qz qw
    (tmp_path / "transforms.json").write_text(
        json.dumps(
            {
                "frames": [
                    {"file_path": "./images/a.png", "transform_matrix": np.eye(4).tolist()},
                    {"file_path": "./images/b.png", "transform_matrix": world_from_cam_opencv_to_opengl(WFC).tolist()},
                ]
            }
        )
    )
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        f"1 1 0 0 0 0 0 0 1 a.png\n\n2 {qw} {qx} {qy} {qz} {tx} {ty} {tz} 1 b.png\n100 200 -1\n"
    )
    (tmp_path / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n1305031102.1000 0 0 0 0 0 0 1\n"
        f"1305031102.2100 {' '.join(f'{v:.9f}' for v in (*WFC[:3, 3], *wq))}\n1305031102.3100 0 0 0 0 0 0 1\n"
    )
    (tmp_path / "frame-000000.pose.txt").write_text(_mat(WFC).replace(" ", "\t"))
    return {
        ("world_from_cam", _mat(WFC), None),
        ("cam_from_world", _mat(T), None),
        ("opengl", _mat(world_from_cam_opencv_to_opengl(WFC)), None),
        ("nerf", str(tmp_path / "transforms.json"), "b.png"),
        ("colmap", f"2 {qw} {qx} {qy} {qz} {tx} {ty} {tz} 1 b.png", None),
        ("colmap", str(tmp_path / "images.txt"), "b.png"),
        ("tum", f"1305031102.21 {' '.join(map(str, (*WFC[:3, 3], *wq)))}", None),
        ("tum", str(tmp_path / "groundtruth.txt"), "1305031102.2"),
        ("7scenes", str(tmp_path / "frame-000000.pose.txt"), None),
    }


def test_every_source_gives_the_same_pose(tmp_path):
    for kind, source, name in _sources(tmp_path):
        got = convert_pose(kind, source, name)
        assert np.allclose(got, T, atol=1e-7), (kind, name)


def test_cli_writes_a_prior_that_localize_reads(tmp_path, capsys):
    qx, qy, qz, qw = rotmat_to_quat(T[:3, :3])
    line = f"7 {qw} {qx} {qy} {qz} {T[0, 3]} {T[1, 3]} {T[2, 3]} 1 q.png"
    out = tmp_path / "prior.txt"
    assert main(["pose", "--from", "colmap", line, "-o", str(out)]) == 0
    assert "world_from_cam" in capsys.readouterr().out
    assert np.allclose(read_pose(out), T, atol=1e-9)
    assert main(["pose", "--from", "cam_from_world", _mat(T)]) == 0
    printed = np.array(capsys.readouterr().out.split(), float).reshape(4, 4)
    assert np.allclose(printed, WFC, atol=1e-9)


@pytest.mark.parametrize(
    "kind, source, name, msg",
    [
        ("nerf", "transforms.json", "zzz.png", "no frame"),
        ("colmap", "1 2 3", None, "QW QX QY QZ"),
        ("opengl", "1 0 0 0 0 2 0 0 0 0 1 0 0 0 0 1", None, "not a rotation"),
        ("tum", "0 0 0 0 0 0 3", None, "unit quaternion"),
    ],
)
def test_bad_sources_are_one_clear_error(tmp_path, kind, source, name, msg):
    _sources(tmp_path)
    if source.endswith(".json"):
        source = str(tmp_path / source)
    with pytest.raises(InputError, match=msg):
        convert_pose(kind, source, name)


def test_a_sequence_folder_names_its_pose_file(tmp_path):
    """A folder (what `favormap build` reads) stands for its pose file: transforms.json, groundtruth.txt,
    FRAME.pose.txt, or the COLMAP model (read by pycolmap)."""
    _sources(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320 240\n")
    for kind, name in (
        ("nerf", "b.png"),
        ("nerf", "images/b"),
        ("colmap", "b.png"),
        ("tum", "1305031102.2"),
        ("7scenes", "frame-000000.color.png"),
    ):
        got = convert_pose(kind, str(tmp_path), name)
        assert np.allclose(got, T, atol=1e-7), (kind, name)
    # Blender-style splits: the split file that lists the frame
    split = tmp_path / "splits"
    split.mkdir()
    frames = json.loads((tmp_path / "transforms.json").read_text())["frames"]
    (split / "transforms_train.json").write_text(json.dumps({"frames": frames[:1]}))
    (split / "transforms_test.json").write_text(json.dumps({"frames": frames[1:]}))
    assert np.allclose(convert_pose("nerf", str(split), "b.png"), T, atol=1e-7)
    # a binary COLMAP model in sparse/0 (pycolmap reads it)
    import pycolmap

    (tmp_path / "points3D.txt").write_text("")
    binary = tmp_path / "bin" / "sparse" / "0"
    binary.mkdir(parents=True)
    pycolmap.Reconstruction(str(tmp_path)).write_binary(str(binary))
    assert np.allclose(convert_pose("colmap", str(tmp_path / "bin"), "b.png"), T, atol=1e-7)
    with pytest.raises(InputError, match="no image named 'zzz.png'"):
        convert_pose("colmap", str(tmp_path / "bin"), "zzz.png")


@pytest.mark.parametrize(
    "kind, name, msg",
    [
        ("opengl", None, "is a folder: --from opengl takes a file"),
        ("nerf", None, "--name is needed"),
        ("nerf", "zzz.png", "no frame with file_path"),
        ("colmap", "zzz.png", "no COLMAP model"),
        ("tum", "1", "no groundtruth.txt"),
        ("7scenes", "frame-000009", "no frame-000009.pose.txt"),
    ],
)
def test_a_folder_without_the_pose_is_one_clear_error(tmp_path, kind, name, msg):
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(InputError, match=msg):
        convert_pose(kind, str(tmp_path), name)
    assert main(["pose", "--from", kind, str(tmp_path)] + (["--name", name] if name else [])) != 0


@pytest.mark.parametrize(
    "frames, msg",
    [
        ([{"file_path": "a.png"}], "no 4x4 transform_matrix"),
        ([{"file_path": "a.png", "transform_matrix": [[1, 2], [3, 4]]}], "is 2x2, not 4x4"),
        ([{"file_path": "a.png", "transform_matrix": "abc"}], "no 4x4 transform_matrix"),
        (["a.png"], "no frame with file_path"),
        ({"a.png": 1}, "no frame with file_path"),
    ],
)
def test_a_damaged_transforms_json_is_one_clear_error(tmp_path, frames, msg):
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    with pytest.raises(InputError, match=msg):
        convert_pose("nerf", str(tmp_path / "transforms.json"), "a.png")
