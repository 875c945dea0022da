"""Sequence readers: round trips, axis conventions, auto-detection and malformed inputs.

Every input is synthesised in tmp_path (tiny noise images, poses from geometry.look_at)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from favormap.errors import SequenceError
from favormap.geometry import inverse, look_at, rotmat_to_quat
from favormap.io import READERS, Camera, Frame, Sequence, detect_format, read_sequence
from favormap.io.readers import nerf, sevenscenes

W, H = 64, 48
RNG = np.random.default_rng(0)


# -- helpers ------------------------------------------------------------------------------------
def write_image(path: Path, w: int = W, h: int = H) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), RNG.integers(0, 255, (h, w, 3), dtype=np.uint8))
    return path


def orbit_poses(n: int = 4) -> list[np.ndarray]:
    """cam_from_world of cameras around the origin, all looking at it (world z up)."""
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.3
        eye = (4 * math.cos(a), 4 * math.sin(a), 1.0 + 0.5 * i)
        out.append(look_at(eye, (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)))
    return out


def project(cam: Camera, cam_from_world: np.ndarray, X) -> tuple[np.ndarray, float]:
    """Pinhole pixel (COLMAP convention) and depth of world point X."""
    x = cam_from_world[:3, :3] @ np.asarray(X, float) + cam_from_world[:3, 3]
    uv = cam.K @ (x / x[2])
    return uv[:2], float(x[2])


def assert_looks_at_origin(seq: Sequence) -> None:
    for f in seq.frames:
        cam = seq.cameras[f.camera_id]
        uv, z = project(cam, f.cam_from_world, (0, 0, 0))
        assert z > 0, f.name
        np.testing.assert_allclose(uv, cam.principal_point, atol=1e-6)


def assert_same_poses(seq: Sequence, expected: list[np.ndarray], atol=1e-12) -> None:
    assert len(seq) == len(expected)
    for f, T in zip(seq.frames, expected):
        assert f.cam_from_world.shape == (4, 4) and f.cam_from_world.dtype == np.float64
        np.testing.assert_allclose(f.cam_from_world, T, atol=atol, rtol=0)


def assert_axes(seq: Sequence, frame: int, right, up) -> None:
    """World direction ``right`` appears right of the image centre, ``up`` above it (OpenCV axes)."""
    f = seq.frames[frame]
    cam = seq.cameras[f.camera_id]
    cx, cy = cam.principal_point
    (u, v), z = project(cam, f.cam_from_world, np.asarray(right, float) * 0.5)
    assert z > 0 and u > cx + 1 and abs(v - cy) < 1e-6
    (u, v), z = project(cam, f.cam_from_world, np.asarray(up, float) * 0.5)
    assert z > 0 and v < cy - 1 and abs(u - cx) < 1e-6


def fmt(x) -> str:
    return repr(float(x))


# -- NeRF ---------------------------------------------------------------------------------------
def test_nerf_axes_handmade(tmp_path):
    """An OpenGL camera at (0, 0, 5) with identity rotation looks down -z at the origin, +y up."""
    write_image(tmp_path / "images" / "a.png")
    data = {
        "fl_x": 50.0,
        "fl_y": 51.0,
        "cx": 30.0,
        "cy": 25.0,
        "w": W,
        "h": H,
        "frames": [
            {"file_path": "images/a.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]}
        ],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    seq = read_sequence(tmp_path)
    assert seq.format == "nerf" and len(seq) == 1
    assert seq.cameras == {0: seq.cameras[0]}
    cam = seq.cameras[0]
    assert cam.model == "PINHOLE" and (cam.width, cam.height) == (W, H)
    np.testing.assert_array_equal(cam.params, [50, 51, 30, 25])
    expected = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1.0]])
    np.testing.assert_array_equal(seq.frames[0].cam_from_world, expected)
    assert_looks_at_origin(seq)
    assert_axes(seq, 0, right=(1, 0, 0), up=(0, 1, 0))
    assert seq.frames[0].name == "images/a.png"


def test_nerf_roundtrip_and_writer(tmp_path):
    poses = orbit_poses(4)
    cam = Camera("OPENCV", W, H, [50.0, 52.0, 31.5, 24.25, 0.01, -0.02, 0.001, 0.002])
    frames = []
    for i, T in enumerate(poses):
        write_image(tmp_path / "images" / f"{i:03d}.jpg")
        frames.append(Frame(f"images/{i:03d}.jpg", tmp_path / "images" / f"{i:03d}.jpg", 0, T))
    nerf.write(Sequence(tmp_path, "x", {0: cam}, frames), tmp_path)
    # hand-made expectation: the file holds camera-to-world in OpenGL axes
    data = json.loads((tmp_path / "transforms.json").read_text())
    gl = np.array(data["frames"][1]["transform_matrix"])
    np.testing.assert_allclose(gl, inverse(poses[1]) @ np.diag([1, -1, -1, 1.0]), atol=1e-12)
    assert detect_format(tmp_path) == "nerf"
    seq = read_sequence(tmp_path / "transforms.json")  # the descriptor file itself works too
    assert_same_poses(seq, poses)
    assert list(seq.cameras) == [0] and seq.cameras[0].model == "OPENCV"
    np.testing.assert_array_equal(seq.cameras[0].params, cam.params)
    assert_looks_at_origin(seq)
    assert [f.name for f in seq.frames] == [f.name for f in frames]


def test_nerf_blender_style(tmp_path):
    """Split files, extension-less paths, camera_angle_x without w/h, k3, per-frame intrinsics."""
    poses = orbit_poses(3)
    for i in range(3):
        write_image(tmp_path / ("train" if i < 2 else "test") / f"r_{i}.png")
    gl = [(inverse(T) @ np.diag([1, -1, -1, 1.0])).tolist() for T in poses]
    angle = 2 * math.atan(W / 2 / 40.0)
    train = {
        "camera_angle_x": angle,
        "k1": 0.1,
        "k3": 0.05,
        "frames": [
            {"file_path": "./train/r_0", "transform_matrix": gl[0]},
            {"file_path": "./train/r_1", "transform_matrix": gl[1], "fl_x": 60.0, "cx": 30.0},
        ],
    }
    test = {"camera_angle_x": angle, "frames": [{"file_path": "./test/r_2", "transform_matrix": gl[2]}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(train))
    (tmp_path / "transforms_test.json").write_text(json.dumps(test))
    seq = read_sequence(tmp_path)
    assert seq.format == "nerf"
    assert seq.extra["split"] == ["train", "train", "test"]
    assert [f.name for f in seq.frames] == ["train/r_0.png", "train/r_1.png", "test/r_2.png"]
    assert_same_poses(seq, poses)
    c0, c1, c2 = (seq.cameras[f.camera_id] for f in seq.frames)
    assert len(seq.cameras) == 3
    assert c0.model == "FULL_OPENCV" and (c0.width, c0.height) == (W, H)
    np.testing.assert_allclose(c0.params, [40, 40, 32, 24, 0.1, 0, 0, 0, 0.05, 0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(c1.params[:4], [60, 60, 30, 24])
    assert c2.model == "PINHOLE"
    np.testing.assert_allclose(c2.params, [40, 40, 32, 24], atol=1e-9)


def _nerf_file(tmp_path, frames, **top):
    write_image(tmp_path / "a.png")
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 50, "w": W, "h": H, **top, "frames": frames}))


@pytest.mark.parametrize(
    "case",
    [
        "broken",
        "empty",
        "no_matrix",
        "nan",
        "inf_focal",
        "not_rigid",
        "bad_shape",
        "no_file_path",
        "frames_not_list",
        "unsupported_model",
        "no_focal",
        "string_focal",
    ],
)
def test_nerf_malformed(tmp_path, case):
    good = np.eye(4).tolist()
    if case == "broken":
        write_image(tmp_path / "a.png")
        (tmp_path / "transforms.json").write_text('{"frames": [ {"file_path": "a.png", ')
    elif case == "empty":
        _nerf_file(tmp_path, [])
    elif case == "no_matrix":
        _nerf_file(tmp_path, [{"file_path": "a.png"}])
    elif case == "nan":
        bad = np.eye(4)
        bad[0, 3] = np.nan
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": bad.tolist()}])
    elif case == "inf_focal":
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": good}], fl_x=float("inf"))
    elif case == "not_rigid":
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": (2 * np.eye(4)).tolist()}])
    elif case == "bad_shape":
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": [[1, 0], [0, 1]]}])
    elif case == "no_file_path":
        _nerf_file(tmp_path, [{"transform_matrix": good}])
    elif case == "frames_not_list":
        _nerf_file(tmp_path, {"a": 1})
    elif case == "unsupported_model":
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": good}], camera_model="FISHEYE624")
    elif case == "no_focal":
        write_image(tmp_path / "a.png")
        (tmp_path / "transforms.json").write_text(
            json.dumps({"frames": [{"file_path": "a.png", "transform_matrix": good}]})
        )
    elif case == "string_focal":
        _nerf_file(tmp_path, [{"file_path": "a.png", "transform_matrix": good}], fl_x="fifty")
    with pytest.raises(SequenceError) as e:
        read_sequence(tmp_path)
    assert "transforms.json" in str(e.value)


def test_nerf_missing_image(tmp_path):
    write_image(tmp_path / "a.png")
    _nerf_file(
        tmp_path,
        [
            {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
            {"file_path": "b.png", "transform_matrix": np.eye(4).tolist()},
        ],
    )
    with pytest.raises(SequenceError, match="missing"):
        read_sequence(tmp_path)


# -- 7-Scenes -----------------------------------------------------------------------------------
def _write_7scenes(root: Path, poses_by_seq: dict[int, list[np.ndarray]]) -> None:
    for s, poses in poses_by_seq.items():
        for i, T in enumerate(poses):
            write_image(root / f"seq-{s:02d}" / f"frame-{i:06d}.color.png")
            wfc = inverse(T)  # the pose file is camera-to-world
            (root / f"seq-{s:02d}" / f"frame-{i:06d}.pose.txt").write_text(
                "".join("\t".join(fmt(v) for v in row) + "\n" for row in wfc)
            )


def test_7scenes_axes_and_defaults(tmp_path):
    # camera at (0, 0, -5), identity rotation: looks along +z at the origin, y down
    T = np.eye(4)
    T[2, 3] = 5.0
    _write_7scenes(tmp_path, {1: [T]})
    seq = read_sequence(tmp_path)
    assert seq.format == "7scenes"
    np.testing.assert_array_equal(seq.frames[0].cam_from_world, T)
    cam = seq.cameras[0]
    # default 525/320/240 at 640x480 (the RGB camera's focal), rescaled to the 64x48 images
    assert cam.model == "PINHOLE" and (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params, [52.5, 52.5, 32, 24])
    assert_looks_at_origin(seq)
    assert_axes(seq, 0, right=(1, 0, 0), up=(0, -1, 0))


def test_7scenes_roundtrip_writer_split(tmp_path):
    poses = orbit_poses(4)
    names = [f"seq-{1 + i // 2:02d}/frame-{i % 2:06d}.color.png" for i in range(4)]
    for n in names:
        write_image(tmp_path / n)
    cam = Camera("PINHOLE", W, H, [50.0, 51.0, 31.0, 23.0])
    frames = [Frame(n, tmp_path / n, 0, T) for n, T in zip(names, poses)]
    sevenscenes.write(Sequence(tmp_path, "x", {0: cam}, frames), tmp_path)
    (tmp_path / "TrainSplit.txt").write_text("sequence1\n")
    (tmp_path / "TestSplit.txt").write_text("sequence2\n")
    assert detect_format(tmp_path) == "7scenes"
    seq = read_sequence(tmp_path)
    assert [f.name for f in seq.frames] == names
    assert_same_poses(seq, poses)
    assert seq.cameras[0].model == "PINHOLE"
    np.testing.assert_array_equal(seq.cameras[0].params, cam.params)
    assert seq.extra["split"] == ["train", "train", "test", "test"]
    assert_looks_at_origin(seq)
    # a single seq-XX folder as the root
    one = read_sequence(tmp_path / "seq-02")
    assert one.format == "7scenes" and [f.name for f in one.frames] == [
        "frame-000000.color.png",
        "frame-000001.color.png",
    ]
    assert_same_poses(one, poses[2:])


def test_7scenes_distorted_camera_file(tmp_path):
    poses = orbit_poses(2)
    names = [f"seq-01/frame-{i:06d}.color.png" for i in range(2)]
    for n in names:
        write_image(tmp_path / n)
    cam = Camera("OPENCV", W, H, [50.0, 51.0, 31.0, 23.0, 0.1, 0.01, 0.001, 0.0])
    sevenscenes.write(
        Sequence(tmp_path, "x", {0: cam}, [Frame(n, tmp_path / n, 0, T) for n, T in zip(names, poses)]), tmp_path
    )
    seq = read_sequence(tmp_path)
    assert seq.cameras[0].model == "OPENCV"
    np.testing.assert_array_equal(seq.cameras[0].params, cam.params)


def test_7scenes_nonfinite_pose_is_skipped(tmp_path):
    _write_7scenes(tmp_path, {1: orbit_poses(3)})
    (tmp_path / "seq-01" / "frame-000001.pose.txt").write_text("inf inf inf inf\n" * 4)
    seq = read_sequence(tmp_path)
    assert [f.name for f in seq.frames] == ["seq-01/frame-000000.color.png", "seq-01/frame-000002.color.png"]
    assert seq.extra["skipped"] == ["seq-01/frame-000001.color.png"]
    # ... but a sequence with no usable pose is an error
    for i in (0, 2):
        (tmp_path / "seq-01" / f"frame-{i:06d}.pose.txt").write_text("-1.#IND000e+000 " * 16)
    with pytest.raises(SequenceError, match="inf/nan"):
        read_sequence(tmp_path)


@pytest.mark.parametrize(
    "case", ["missing_pose", "missing_image", "short_pose", "text_pose", "bad_K", "not_rigid", "bad_split"]
)
def test_7scenes_malformed(tmp_path, case):
    _write_7scenes(tmp_path, {1: orbit_poses(2)})
    d = tmp_path / "seq-01"
    if case == "missing_pose":
        (d / "frame-000001.pose.txt").unlink()
        match = "frame-000001.pose.txt"
    elif case == "missing_image":
        (d / "frame-000001.color.png").unlink()
        match = "frame-000001.color.png"
    elif case == "short_pose":
        (d / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
        match = "frame-000001.pose.txt"
    elif case == "text_pose":
        (d / "frame-000001.pose.txt").write_text("hello world\n")
        match = "frame-000001.pose.txt"
    elif case == "not_rigid":
        (d / "frame-000001.pose.txt").write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n")
        match = "frame-000001.pose.txt"
    elif case == "bad_K":
        (tmp_path / "camera.txt").write_text("1 2 3\n4 5 6\n")
        match = "camera.txt"
    elif case == "bad_split":
        (tmp_path / "TrainSplit.txt").write_text("whatever\n")
        match = "TrainSplit.txt"
    with pytest.raises(SequenceError, match=match):
        read_sequence(tmp_path)


# -- COLMAP -------------------------------------------------------------------------------------
def _colmap_model(tmp_path: Path, model_dir: str, binary: bool, model="OPENCV", params=None, image_dir="images"):
    import pycolmap

    from favormap.geometry import to_rigid3d

    poses = orbit_poses(3)
    params = params or [50.0, 52.0, 31.5, 24.5, 0.01, -0.02, 0.001, 0.002]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=3))
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[40, 40, 32, 24], camera_id=7)
    )
    names = ["b.png", "sub/a.png", "c.png"]
    for i, (n, T) in enumerate(zip(names, poses)):
        write_image(tmp_path / image_dir / n)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=n, camera_id=3 if i < 2 else 7, image_id=i + 1), to_rigid3d(T)
        )
    # an unregistered image is not a frame
    rec.add_image_with_trivial_frame(pycolmap.Image(name="unreg.png", camera_id=3, image_id=10))
    out = tmp_path / model_dir
    out.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(out))
    return dict(zip(names, poses)), params


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("model_dir", ["sparse/0", "sparse", "colmap/sparse/0", "."])
def test_colmap_roundtrip(tmp_path, binary, model_dir):
    expected, params = _colmap_model(tmp_path, model_dir, binary)
    assert detect_format(tmp_path) == "colmap"
    seq = read_sequence(tmp_path)
    assert seq.format == "colmap"
    order = sorted(expected)
    assert [f.name for f in seq.frames] == [f"images/{n}" for n in order]
    assert_same_poses(seq, [expected[n] for n in order])
    assert sorted(seq.cameras) == [3, 7]
    assert seq.cameras[3].model == "OPENCV" and (seq.cameras[3].width, seq.cameras[3].height) == (W, H)
    np.testing.assert_allclose(seq.cameras[3].params, params, rtol=1e-15)
    assert [f.camera_id for f in seq.frames] == [3, 7, 3]  # b, c, sub/a
    assert_looks_at_origin(seq)


def test_colmap_images_in_root(tmp_path):
    expected, _ = _colmap_model(tmp_path, "sparse/0", True, image_dir=".")
    seq = read_sequence(tmp_path)
    assert [f.name for f in seq.frames] == sorted(expected)


def test_colmap_unsupported_model(tmp_path):
    params = [50.0, 50.0, 32, 24] + [0.01] * 8
    _colmap_model(tmp_path, "sparse/0", False, model="THIN_PRISM_FISHEYE", params=params)
    with pytest.raises(SequenceError, match="THIN_PRISM_FISHEYE"):
        read_sequence(tmp_path)


def test_colmap_broken(tmp_path):
    _colmap_model(tmp_path, "sparse/0", False)
    (tmp_path / "sparse/0/cameras.txt").write_text("3 OPENCV sixty-four\n")
    with pytest.raises(SequenceError, match="COLMAP"):
        read_sequence(tmp_path)


def test_colmap_no_registered_images(tmp_path):
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[40, 40, 32, 24], camera_id=1)
    )
    rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", camera_id=1, image_id=1))
    write_image(tmp_path / "images" / "a.png")
    (tmp_path / "sparse").mkdir()
    rec.write_text(str(tmp_path / "sparse"))
    with pytest.raises(SequenceError, match="no registered images"):
        read_sequence(tmp_path)


# -- Cambridge ----------------------------------------------------------------------------------
HEADER = "Visual Landmark Dataset V1\nImageFile, Camera Position [X Y Z W P Q R]\n\n"


def _cambridge_line(name: str, T: np.ndarray) -> str:
    R = T[:3, :3]
    C = -R.T @ T[:3, 3]
    x, y, z, w = rotmat_to_quat(R)  # the quaternion of cam_from_world's rotation
    return f"{name} " + " ".join(fmt(v) for v in (*C, w, x, y, z)) + "\n"


def test_cambridge_axes_handmade(tmp_path):
    # q = 90 deg about y: R = [[0,0,1],[0,1,0],[-1,0,0]]; its optical axis R^T e_z = -x: a camera at
    # C = (5, 0, 0) looks at the origin
    write_image(tmp_path / "seq1" / "frame00001.png")
    s = math.sqrt(0.5)
    (tmp_path / "dataset_train.txt").write_text(HEADER + f"seq1/frame00001.png 5 0 0 {s} 0 {s} 0\n")
    seq = read_sequence(tmp_path)
    assert seq.format == "cambridge"
    expected = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 5], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(seq.frames[0].cam_from_world, expected, atol=1e-12)
    assert_looks_at_origin(seq)
    cam = seq.cameras[0]
    assert cam.model == "SIMPLE_PINHOLE" and (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params, [0.87 * W, W / 2, H / 2])
    assert seq.extra["split"] == ["train"]


def test_cambridge_roundtrip_split_camera_file(tmp_path):
    poses = orbit_poses(4)
    names = [f"seq{1 + i // 2}/frame{i:05d}.png" for i in range(4)]
    for n in names:
        write_image(tmp_path / n)
    (tmp_path / "dataset_train.txt").write_text(
        HEADER + "".join(_cambridge_line(n, T) for n, T in zip(names[:3], poses))
    )
    (tmp_path / "dataset_test.txt").write_text(HEADER + _cambridge_line(names[3], poses[3]))
    assert detect_format(tmp_path) == "cambridge"
    seq = read_sequence(tmp_path)
    assert [f.name for f in seq.frames] == names
    assert seq.extra["split"] == ["train", "train", "train", "test"]
    assert_same_poses(seq, poses, atol=1e-12)
    assert_looks_at_origin(seq)
    # a COLMAP camera file given at twice the size is rescaled to the images
    (tmp_path / "cameras.txt").write_text("# Camera list\n1 PINHOLE 128 96 100 102 64 48\n")
    cam = read_sequence(tmp_path).cameras[0]
    assert cam.model == "PINHOLE" and (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params, [50, 51, 32, 24])


@pytest.mark.parametrize("case", ["nan", "short", "text", "zero_quat", "duplicate", "two_cameras", "bad_model"])
def test_cambridge_malformed(tmp_path, case):
    write_image(tmp_path / "seq1" / "a.png")
    line = _cambridge_line("seq1/a.png", orbit_poses(1)[0])
    body = {
        "nan": "seq1/a.png 1 2 nan 1 0 0 0\n",
        "short": "seq1/a.png 1 2 3\n",
        "text": "seq1/a.png 1 2 x 1 0 0 0\n",
        "zero_quat": "seq1/a.png 1 2 3 0 0 0 0\n",
        "duplicate": line + line,
    }.get(case, line)
    (tmp_path / "dataset_train.txt").write_text(HEADER + body)
    if case == "two_cameras":
        (tmp_path / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 32 24\n2 PINHOLE 64 48 50 50 32 24\n")
    if case == "bad_model":
        (tmp_path / "camera.txt").write_text("1 FISHEYE_WHATEVER 64 48 50 50 32 24\n")
    with pytest.raises(SequenceError, match=r"dataset_train\.txt|camera"):
        read_sequence(tmp_path)


# -- TUM RGB-D ----------------------------------------------------------------------------------
def _write_tum(root: Path, poses, offsets=None, camera_line=None):
    rgb = ["# color images", "# timestamp filename"]
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for i, T in enumerate(poses):
        t = 1305031102.0 + 0.1 * i
        write_image(root / "rgb" / f"{t:.6f}.png")
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        wfc = inverse(T)
        q = rotmat_to_quat(wfc[:3, :3])
        off = 0.005 if offsets is None else offsets[i]
        gt.append(f"{t + off:.6f} " + " ".join(fmt(v) for v in (*wfc[:3, 3], *q)))
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if camera_line:
        (root / "camera.txt").write_text(camera_line + "\n")


def test_tum_roundtrip_association(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    poses = orbit_poses(4)
    _write_tum(root, poses, offsets=[0.005, -0.01, 0.5, 0.0])  # frame 2 has no pose within 0.02 s
    assert detect_format(root) == "tum"
    seq = read_sequence(root)
    assert seq.format == "tum" and len(seq) == 3 and seq.extra["unassociated"] == 1
    assert_same_poses(seq, [poses[0], poses[1], poses[3]], atol=1e-12)
    assert_looks_at_origin(seq)
    # freiburg1 calibration (OpenCV principal point + 0.5), rescaled from 640x480 to 64x48
    cam = seq.cameras[0]
    assert cam.model == "FULL_OPENCV" and (cam.width, cam.height) == (W, H)
    np.testing.assert_allclose(cam.params[:4], [51.73, 51.65, 31.91, 25.58], atol=1e-9)
    np.testing.assert_allclose(cam.params[4:9], [0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
    assert seq.extra["intrinsics"] == "freiburg1"


def test_tum_axes_and_camera_file(tmp_path):
    # world_from_cam rotation Ry(-90 deg): optical axis = -x; camera at (5, 0, 0) looks at the origin
    root = tmp_path / "seq"
    write_image(root / "rgb" / "1.png")
    s = math.sqrt(0.5)
    (root / "rgb.txt").write_text("1.000 rgb/1.png\n")
    (root / "groundtruth.txt").write_text(f"1.001 5 0 0 0 {-s} 0 {s}\n")
    (root / "camera.txt").write_text("1 PINHOLE 64 48 50 51 30 20\n")
    seq = read_sequence(root)
    expected = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 5], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(seq.frames[0].cam_from_world, expected, atol=1e-12)
    np.testing.assert_array_equal(seq.cameras[0].params, [50, 51, 30, 20])
    assert_looks_at_origin(seq)
    assert_axes(seq, 0, right=(0, 0, 1), up=(0, -1, 0))


@pytest.mark.parametrize("case", ["none_associated", "nan", "short_gt", "text_ts", "no_rgb"])
def test_tum_malformed(tmp_path, case):
    _write_tum(tmp_path, orbit_poses(2), offsets=[1.0, 1.0] if case == "none_associated" else None)
    if case == "nan":
        txt = (tmp_path / "groundtruth.txt").read_text().splitlines()
        txt[-1] = " ".join(txt[-1].split()[:3] + ["nan"] + txt[-1].split()[4:])
        (tmp_path / "groundtruth.txt").write_text("\n".join(txt) + "\n")
    elif case == "short_gt":
        (tmp_path / "groundtruth.txt").write_text("1305031102.0 1 2 3\n")
    elif case == "text_ts":
        (tmp_path / "rgb.txt").write_text("abc rgb/x.png\n")
    elif case == "no_rgb":
        (tmp_path / "rgb.txt").write_text("# nothing\n")
    with pytest.raises(SequenceError, match=r"rgb\.txt|groundtruth\.txt"):
        read_sequence(tmp_path)


# -- LLFF ---------------------------------------------------------------------------------------
def _llff_rows(poses, hwf, bounds=(0.5, 10.0)):
    rows = []
    for T in poses:
        wfc = inverse(T)
        right, down, fwd, centre = wfc[:3, 0], wfc[:3, 1], wfc[:3, 2], wfc[:3, 3]
        M = np.stack([down, right, -fwd, centre, np.asarray(hwf, float)], axis=1)  # LLFF: [down, right, back]
        rows.append(np.concatenate([M.ravel(), bounds]))
    return np.array(rows)


def test_llff_roundtrip(tmp_path):
    poses = orbit_poses(3)
    for i in range(3):
        write_image(tmp_path / "images" / f"IMG_{i:04d}.JPG")
    np.save(tmp_path / "poses_bounds.npy", _llff_rows(poses, (H, W, 50.0)))
    assert detect_format(tmp_path) == "llff"
    seq = read_sequence(tmp_path)
    assert seq.format == "llff"
    assert [f.name for f in seq.frames] == [f"images/IMG_{i:04d}.JPG" for i in range(3)]
    assert_same_poses(seq, poses, atol=1e-12)
    assert seq.cameras[0].model == "SIMPLE_PINHOLE"
    np.testing.assert_array_equal(seq.cameras[0].params, [50, W / 2, H / 2])
    assert seq.extra["bounds"] == [[0.5, 10.0]] * 3
    assert_looks_at_origin(seq)


def test_llff_axes_handmade_and_downsampled(tmp_path):
    # camera at (0, 0, 5) looking at the origin along -z with +y up: LLFF columns
    # [down, right, back] = [-y, +x, +z]
    write_image(tmp_path / "images_4" / "a.png")
    M = np.array([[0, 1, 0, 0, 4 * H], [-1, 0, 0, 0, 4 * W], [0, 0, 1, 5, 200.0]])
    np.save(tmp_path / "poses_bounds.npy", np.concatenate([M.ravel(), [1, 9]])[None])
    seq = read_sequence(tmp_path)
    expected = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1.0]])
    np.testing.assert_array_equal(seq.frames[0].cam_from_world, expected)
    cam = seq.cameras[0]
    assert (cam.width, cam.height) == (W, H) and seq.extra["images_dir"] == "images_4"
    np.testing.assert_allclose(cam.params, [50, W / 2, H / 2])
    assert_looks_at_origin(seq)
    assert_axes(seq, 0, right=(1, 0, 0), up=(0, 1, 0))


@pytest.mark.parametrize("case", ["count", "nan", "shape", "broken", "no_images"])
def test_llff_malformed(tmp_path, case):
    rows = _llff_rows(orbit_poses(2), (H, W, 50.0))
    if case != "no_images":
        for i in range(2 if case != "count" else 1):
            write_image(tmp_path / "images" / f"{i}.png")
    if case == "nan":
        rows[1, 3] = np.nan
    if case == "shape":
        rows = rows[:, :15]
    np.save(tmp_path / "poses_bounds.npy", rows)
    if case == "broken":
        (tmp_path / "poses_bounds.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(SequenceError, match=r"poses_bounds\.npy|images"):
        read_sequence(tmp_path)


# -- detection ----------------------------------------------------------------------------------
def test_all_readers_registered():
    assert {"nerf", "colmap", "7scenes", "cambridge", "tum", "llff"} <= set(READERS)


def test_detect_unknown_and_empty(tmp_path):
    with pytest.raises(SequenceError, match="not found"):
        read_sequence(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match="empty"):
        read_sequence(tmp_path / "empty")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("hello")
    write_image(tmp_path / "other" / "a.png")
    with pytest.raises(SequenceError, match="cannot recognise"):
        read_sequence(tmp_path / "other")
    with pytest.raises(SequenceError, match="unknown sequence format"):
        read_sequence(tmp_path / "other", format="nope")
    for name, mod in READERS.items():
        assert not mod.detect(tmp_path / "other"), name


@pytest.mark.parametrize("fmt_name", ["nerf", "colmap", "7scenes", "cambridge", "tum", "llff"])
def test_forced_format_on_wrong_folder(tmp_path, fmt_name):
    """Forcing a reader on a folder of another format gives a SequenceError, not a crash."""
    write_image(tmp_path / "a.png")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(SequenceError):
        read_sequence(tmp_path, format=fmt_name)


def _build(fmt_name: str, root: Path) -> list[Path]:
    """A valid 3-frame sequence of ``fmt_name`` in ``root``; returns its image paths in frame order."""
    poses = orbit_poses(3)
    if fmt_name == "nerf":
        imgs = [write_image(root / "images" / f"{i}.png") for i in range(3)]
        cam = Camera("PINHOLE", W, H, [50.0, 50, 32, 24])
        nerf.write(
            Sequence(
                root, "x", {0: cam}, [Frame(f"images/{i}.png", p, 0, T) for i, (p, T) in enumerate(zip(imgs, poses))]
            ),
            root,
        )
    elif fmt_name == "7scenes":
        _write_7scenes(root, {1: poses})
        imgs = [root / "seq-01" / f"frame-{i:06d}.color.png" for i in range(3)]
    elif fmt_name == "colmap":
        expected, _ = _colmap_model(root, "sparse/0", True)
        imgs = [root / "images" / n for n in sorted(expected)]
    elif fmt_name == "cambridge":
        imgs = [write_image(root / "seq1" / f"{i}.png") for i in range(3)]
        (root / "dataset_train.txt").write_text(
            HEADER + "".join(_cambridge_line(f"seq1/{i}.png", T) for i, T in enumerate(poses))
        )
    elif fmt_name == "tum":
        _write_tum(root, poses)
        imgs = sorted((root / "rgb").iterdir())
    elif fmt_name == "llff":
        imgs = [write_image(root / "images" / f"{i}.png") for i in range(3)]
        np.save(root / "poses_bounds.npy", _llff_rows(poses, (H, W, 50.0)))
    return imgs


@pytest.mark.parametrize("which", [0, 2])
@pytest.mark.parametrize("fmt_name", ["nerf", "colmap", "7scenes", "cambridge", "tum", "llff"])
def test_missing_image_file(tmp_path, fmt_name, which):
    imgs = _build(fmt_name, tmp_path)
    seq = read_sequence(tmp_path)
    assert seq.format == fmt_name and len(seq) == 3
    assert [Path(f.image_path) for f in seq.frames] == imgs
    imgs[which].unlink()
    with pytest.raises(SequenceError):
        read_sequence(tmp_path)
