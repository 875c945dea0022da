"""Real inputs: files written exactly as the real datasets and tools write them, near-rigid
rotations (projected onto SO(3) at read time, refused beyond the one tolerance), and a build
that refuses non-rigid poses before any image is read."""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from favormap.errors import SequenceError
from favormap.geometry import ROTATION_TOL, inverse, look_at, rotation_deviation, rotmat_to_quat
from favormap.io import Camera, Frame, Sequence, read_sequence
from favormap.mapfile.writer import check_frames

W, H = 64, 48
RNG = np.random.default_rng(1)
NEAR = 2e-4  # the deviation of the 7-Scenes pose files (max |R^T R - I|)
FAR = 6e-3  # beyond ROTATION_TOL


def write_image(path: Path, w: int = W, h: int = H) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), RNG.integers(0, 255, (h, w, 3), dtype=np.uint8))
    return path


def orbit(n: int = 3) -> list[np.ndarray]:
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.3
        out.append(look_at((4 * math.cos(a), 4 * math.sin(a), 1.0 + 0.5 * i), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)))
    return out


def skew_rotation(R: np.ndarray, dev: float) -> np.ndarray:
    """``R (I + S)`` with a symmetric S, so that max |R'^T R' - I| is about ``dev``."""
    S = np.array([[0.5, 0.25, -0.5], [0.25, -0.5, 0.5], [-0.5, 0.5, 0.25]]) * dev
    return R @ (np.eye(3) + S)


def skew_pose(T: np.ndarray, dev: float) -> np.ndarray:
    T = T.copy()
    T[:3, :3] = skew_rotation(T[:3, :3], dev)
    return T


def msvc(v: float) -> str:
    """A number as the 7-Scenes files print it (MSVC printf: three exponent digits)."""
    s = f"{v:.7e}"
    mant, exp = s.split("e")
    return f"{mant}e{exp[0]}{int(exp[1:]):03d}"


def write_7scenes_pose(path: Path, world_from_cam: np.ndarray) -> None:
    # as shipped: 4 lines of tab-separated numbers, each line ending with a tab
    path.write_text("".join("".join(msvc(v) + "\t" for v in row) + "\n" for row in world_from_cam))


# -- per-reader writers of near-rigid sequences --------------------------------------------------
def _seq_7scenes(root, poses, dev):
    for i, T in enumerate(poses):
        write_image(root / "seq-01" / f"frame-{i:06d}.color.png")
        cv2.imwrite(str(root / "seq-01" / f"frame-{i:06d}.depth.png"), np.zeros((H, W), np.uint16))
        write_7scenes_pose(root / "seq-01" / f"frame-{i:06d}.pose.txt", skew_pose(inverse(T), dev))
    (root / "TrainSplit.txt").write_text("sequence1\n")


def _seq_nerf(root, poses, dev):
    import json

    from favormap.geometry import world_from_cam_opencv_to_opengl

    frames = []
    for i, T in enumerate(poses):
        write_image(root / "images" / f"{i:04d}.jpg")
        gl = skew_pose(world_from_cam_opencv_to_opengl(inverse(T)), dev)
        frames.append({"file_path": f"./images/{i:04d}.jpg", "sharpness": 31.5, "transform_matrix": gl.tolist()})
    (root / "transforms.json").write_text(
        json.dumps(
            {
                "camera_angle_x": 1.1,
                "camera_angle_y": 0.9,
                "fl_x": 50.0,
                "fl_y": 50.0,
                "k1": 0.01,
                "k2": -0.002,
                "p1": 0.0,
                "p2": 0.0,
                "cx": 32.0,
                "cy": 24.0,
                "w": W,
                "h": H,
                "aabb_scale": 4,
                "frames": frames,
            },
            indent=2,
        )
    )


def _llff_row(T, hwf, bounds=(1.5, 12.0), dev=0.0):
    wfc = inverse(T)
    right, down, fwd, centre = wfc[:3, 0], wfc[:3, 1], wfc[:3, 2], wfc[:3, 3]
    R = skew_rotation(np.stack([down, right, -fwd], 1), dev)  # LLFF columns: [down, right, backwards]
    return np.concatenate([np.concatenate([R, centre[:, None], np.asarray(hwf, float)[:, None]], 1).ravel(), bounds])


def _seq_llff(root, poses, dev):
    # as LLFF's imgs2poses writes it: float64 N x 17, hwf of the full-size images, images_8/ at 1/8
    for i in range(len(poses)):
        write_image(root / "images_8" / f"IMG_{4026 + i}.png")
    np.save(root / "poses_bounds.npy", np.stack([_llff_row(T, (8 * H, 8 * W, 8 * 50.0), dev=dev) for T in poses]))


def _seq_favormap(root, poses, dev):
    from favormap.io.readers import favormap_layout

    frames = [
        Frame(f"images/{i:06d}.png", write_image(root / "images" / f"{i:06d}.png"), 0, T) for i, T in enumerate(poses)
    ]
    favormap_layout.write(Sequence(root, "favormap", {0: Camera("PINHOLE", W, H, [50, 50, 32, 24])}, frames), root)
    import json

    data = json.loads((root / "sequence.json").read_text())
    for fr, T in zip(data["frames"], poses):
        fr["cam_from_world"] = skew_pose(T, dev).tolist()
    (root / "sequence.json").write_text(json.dumps(data))


def _scaled_quat(q, dev):
    return np.asarray(q) * (1 + dev) ** 0.25  # |q|^4 - 1 = dev


def _seq_tum(root, poses, dev):
    # as the TUM benchmark ships it: 100 Hz ground truth with 4 decimals, 30 Hz images whose
    # timestamps match no ground-truth timestamp exactly, extra files beside them
    gt = ["# ground truth trajectory", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp tx ty tz qx qy qz qw"]
    rgb = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    t0 = 1305031098.6659
    for i, _T in enumerate(poses):
        t_img = t0 + 0.4 + i / 30 + 0.0013
        write_image(root / "rgb" / f"{t_img:.6f}.png")
        rgb.append(f"{t_img:.6f} rgb/{t_img:.6f}.png")
    for k in range(int(len(poses) / 30 * 100) + 60):
        t = t0 + 0.01 * k
        i = min(len(poses) - 1, max(0, round((t - t0 - 0.4 - 0.0013) * 30)))
        wfc = inverse(poses[i])
        q = _scaled_quat(rotmat_to_quat(wfc[:3, :3]), dev)
        gt.append(f"{t:.4f} " + " ".join(f"{v:.4f}" for v in (*wfc[:3, 3], *q)))
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (root / "depth.txt").write_text("# depth maps\n# file: 'rgbd_dataset_freiburg1_xyz.bag'\n# timestamp filename\n")
    (root / "accelerometer.txt").write_text(
        "# accelerometer data\n# timestamp ax ay az\n1305031098.6659 -0.0 9.8 0.0\n"
    )


def _seq_cambridge(root, poses, dev):
    lines = ["Visual Landmark Dataset V1", "ImageFile, Camera Position [X Y Z W P Q R]", ""]
    for i, T in enumerate(poses):
        write_image(root / "seq1" / f"frame{i + 1:05d}.png")
        C = -T[:3, :3].T @ T[:3, 3]
        x, y, z, w = _scaled_quat(rotmat_to_quat(T[:3, :3]), dev)
        lines.append(f"seq1/frame{i + 1:05d}.png " + " ".join(f"{v:.6f}" for v in (*C, w, x, y, z)))
    (root / "dataset_train.txt").write_text("\r\n".join(lines) + "\r\n")  # the originals have Windows line ends


def _seq_colmap(root, poses, dev):
    """images.txt as COLMAP writes it, with quaternions rounded to 4 decimals and scaled by ``dev``."""
    (root / "sparse" / "0").mkdir(parents=True)
    cams, ims = ["# Camera list with one line of data per camera:"], ["# Image list with two lines of data per image:"]
    for i, T in enumerate(poses):
        write_image(root / "images" / f"{i}.jpg")
        cams.append(f"{i + 1} SIMPLE_RADIAL {W} {H} 50 32 24 0.01")
        x, y, z, w = _scaled_quat(rotmat_to_quat(T[:3, :3]), dev)
        ims += [
            f"{i + 1} {w:.4f} {x:.4f} {y:.4f} {z:.4f} " + " ".join(f"{v:.6f}" for v in T[:3, 3]) + f" {i + 1} {i}.jpg",
            "",
        ]
    (root / "sparse/0/cameras.txt").write_text("\n".join(cams) + "\n")
    (root / "sparse/0/images.txt").write_text("\n".join(ims) + "\n")
    (root / "sparse/0/points3D.txt").write_text("# 3D point list\n")


WRITERS = {
    "7scenes": _seq_7scenes,
    "nerf": _seq_nerf,
    "llff": _seq_llff,
    "favormap": _seq_favormap,
    "tum": _seq_tum,
    "cambridge": _seq_cambridge,
    "colmap": _seq_colmap,
}


def _assert_map_ready(seq: Sequence) -> None:
    for f in seq.frames:
        assert rotation_deviation(f.cam_from_world[:3, :3]) < 1e-12
    names = [f.name for f in seq.frames]
    assert (
        check_frames(
            seq.cameras, names, [f.camera_id for f in seq.frames], np.stack([f.cam_from_world for f in seq.frames])
        )
        == []
    )


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_near_rigid_rotations_are_projected_and_reported(tmp_path, caplog, fmt):
    poses = orbit(3)
    WRITERS[fmt](tmp_path, poses, NEAR if fmt != "colmap" else 0.0)
    with caplog.at_level(logging.INFO, logger="favormap"):
        seq = read_sequence(tmp_path)
    assert seq.format == fmt and len(seq) == 3
    _assert_map_ready(seq)
    for f, T in zip(seq.frames, poses):  # the projection moves a rotation by about the deviation only
        assert np.abs(f.cam_from_world[:3, :3] - T[:3, :3]).max() < 3e-3
    if fmt != "colmap":  # pycolmap normalises quaternions itself
        msgs = [r.getMessage() for r in caplog.records if "projected onto SO(3)" in r.getMessage()]
        assert len(msgs) == 1, caplog.text
        dev = float(msgs[0].split("|R^T R - I| = ")[1].split()[0])
        assert NEAR / 4 < dev < ROTATION_TOL


@pytest.mark.parametrize("fmt", sorted(set(WRITERS) - {"colmap"}))
def test_rotations_beyond_the_tolerance_are_refused_at_read_time(tmp_path, fmt):
    WRITERS[fmt](tmp_path, orbit(3), FAR)
    with pytest.raises(SequenceError, match="tolerance 1e-03"):
        read_sequence(tmp_path)


def test_colmap_binary_model_one_camera_per_image(tmp_path):
    """sparse/0/*.bin as pycolmap writes them, with one camera per image (COLMAP's default)."""
    import pycolmap

    from favormap.geometry import to_rigid3d

    poses = orbit(3)
    rec = pycolmap.Reconstruction()
    for i, T in enumerate(poses):
        write_image(tmp_path / "images" / f"IMG_{i}.JPG")
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[50 + i, 32, 24, 0.01], camera_id=i + 1)
        )
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"IMG_{i}.JPG", camera_id=i + 1, image_id=i + 1), to_rigid3d(T)
        )
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    rec.write_binary(str(tmp_path / "sparse" / "0"))
    assert {p.name for p in (tmp_path / "sparse" / "0").iterdir()} >= {"cameras.bin", "images.bin", "points3D.bin"}
    seq = read_sequence(tmp_path)
    assert seq.format == "colmap" and len(seq.cameras) == 3
    assert [seq.cameras[f.camera_id].params[0] for f in seq.frames] == [50, 51, 52]
    for f, T in zip(seq.frames, poses):
        assert np.allclose(f.cam_from_world, T, atol=1e-9)
    _assert_map_ready(seq)


def test_tum_unmatched_timestamps_take_the_nearest_pose(tmp_path):
    poses = orbit(3)
    _seq_tum(tmp_path, poses, 0.0)
    seq = read_sequence(tmp_path)
    assert seq.extra["unassociated"] == 0 and len(seq) == 3
    for f, T in zip(seq.frames, poses):
        assert np.abs(f.cam_from_world[:3, 3] - T[:3, 3]).max() < 5e-4  # 4 decimals in the file


def test_7scenes_file_as_shipped_reads_exactly(tmp_path):
    poses = orbit(3)
    _seq_7scenes(tmp_path, poses, 0.0)
    assert (
        "e-001\t" in (tmp_path / "seq-01" / "frame-000000.pose.txt").read_text()
        or "e+000\t" in (tmp_path / "seq-01" / "frame-000000.pose.txt").read_text()
    )
    seq = read_sequence(tmp_path)
    assert seq.extra["split"] == ["train"] * 3
    for f, T in zip(seq.frames, poses):
        assert np.allclose(f.cam_from_world, T, atol=1e-6)


def test_build_refuses_non_rigid_poses_before_any_image_is_read(tmp_path, monkeypatch):
    """A Sequence made in Python (no reader) with a pose the writer would refuse: refused first."""
    import favormap.build as build

    def boom(*a, **k):
        raise AssertionError("images were read before the poses were checked")

    monkeypatch.setattr(build, "extract_sequence", boom)
    poses = orbit(3)
    poses[1] = skew_pose(poses[1], 2e-3)
    frames = [Frame(f"{i}.png", write_image(tmp_path / f"{i}.png"), 0, T) for i, T in enumerate(poses)]
    seq = Sequence(tmp_path, "python", {0: Camera("PINHOLE", W, H, [50, 50, 32, 24])}, frames)
    with pytest.raises(SequenceError, match="cannot become a map: 'frames/cam_from_world': 1 value not a rigid"):
        build.build_map(seq)
    frames[1].camera_id = 5  # unknown camera: also before the work
    frames[1].cam_from_world = poses[0]
    with pytest.raises(SequenceError, match="cannot become a map"):
        build.build_map(seq)


def test_near_rigid_7scenes_sequence_builds(small_sequence, tmp_path, capsys):
    """A 7-Scenes-style sequence (pose files as shipped, rotations orthonormal to 2e-4) builds and
    writes its map through the CLI (the map writer refused it after the training before)."""
    from favormap.cli import main
    from favormap.io.readers import sevenscenes
    from favormap.mapfile import Map

    root = tmp_path / "scene"
    frames, src = [], small_sequence.frames[::2]
    for i, f in enumerate(src):
        dst = root / "seq-01" / f"frame-{i:06d}.color.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(f.image_path, dst)
        frames.append(Frame(f"seq-01/frame-{i:06d}.color.png", dst, 0, f.cam_from_world))
    sevenscenes.write(Sequence(root, "7scenes", dict(small_sequence.cameras), frames), root)
    for i, f in enumerate(src):  # rewrite the pose files as the dataset ships them
        write_7scenes_pose(root / "seq-01" / f"frame-{i:06d}.pose.txt", skew_pose(inverse(f.cam_from_world), NEAR))
    out = tmp_path / "map.h5"
    rc = main(
        [
            "build",
            str(root),
            "-o",
            str(out),
            "--resize",
            "0",
            "--quality",
            "fast",
            "--iterations",
            "10",
            "--max-landmarks",
            "40",
            "--min-track",
            "3",
            "--max-keypoints",
            "600",
            "-q",
            "--device",
            "cpu",
        ]
    )
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "projected onto SO(3)" in cap.err and "largest deviation" in cap.err
    with Map.open(out) as m:
        assert m.num_landmarks > 0
