"""TUM RGB-D benchmark sequences.

::

    SEQ/                         (e.g. rgbd_dataset_freiburg1_xyz)
      rgb.txt                    ``timestamp filename`` per line, ``#`` comments
      groundtruth.txt            ``timestamp tx ty tz qx qy qz qw`` (world_from_cam, OpenCV camera axes)
      rgb/...
      camera.txt                 optional: one COLMAP text camera line (overrides the defaults)

Each rgb timestamp takes the pose of the nearest groundtruth timestamp when it is within
``MAX_DT`` = 0.02 s; frames without one are dropped (their count is ``extra["unassociated"]``), and
a sequence where nothing associates is a SequenceError.

Intrinsics: the published TUM calibration, picked by ``freiburg1/2/3`` in the folder name (the
root's name first, then its parent's); no match -> the ROS default (525, 525, 319.5, 239.5):

- freiburg1: FULL_OPENCV fx 517.3 fy 516.5 cx 318.6 cy 255.3, d = 0.2624 -0.9531 -0.0054 0.0026 1.1633
- freiburg2: FULL_OPENCV fx 520.9 fy 521.0 cx 325.1 cy 249.7, d = 0.2312 -0.7849 -0.0033 -0.0001 0.9172
- freiburg3: PINHOLE fx 535.4 fy 539.2 cx 320.1 cy 247.6 (its images are already undistorted)

FULL_OPENCV keeps the significant k3 term (k4..k6 = 0). TUM's principal points come from ROS/OpenCV
calibration (pixel centres at integers), so 0.5 is added to convert to COLMAP's convention. The
image size is read from the first image; a camera given for another size is rescaled to it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import inverse, pose_from_quat_t
from ..types import Camera, Frame, Sequence
from .common import (
    checked_quaternion,
    fit_camera,
    guarded,
    image_size,
    posix_relpath,
    read_single_camera_text,
    text_rows,
)

NAME = "tum"
DESCRIPTOR_FILES = ("rgb.txt", "groundtruth.txt")
MAX_DT = 0.02


def _cv_to_colmap(fx, fy, cx, cy):
    return [fx, fy, cx + 0.5, cy + 0.5]


DEFAULT_CAMERAS = {
    "1": Camera(
        "FULL_OPENCV",
        640,
        480,
        _cv_to_colmap(517.3, 516.5, 318.6, 255.3) + [0.2624, -0.9531, -0.0054, 0.0026, 1.1633, 0, 0, 0],
    ),
    "2": Camera(
        "FULL_OPENCV",
        640,
        480,
        _cv_to_colmap(520.9, 521.0, 325.1, 249.7) + [0.2312, -0.7849, -0.0033, -0.0001, 0.9172, 0, 0, 0],
    ),
    "3": Camera("PINHOLE", 640, 480, _cv_to_colmap(535.4, 539.2, 320.1, 247.6)),
    None: Camera("PINHOLE", 640, 480, _cv_to_colmap(525.0, 525.0, 319.5, 239.5)),
}


def detect(root: Path) -> bool:
    root = Path(root)
    return (root / "rgb.txt").is_file() and (root / "groundtruth.txt").is_file()


def _rows(path: Path, ncols: int, what: str):
    for where, tok in text_rows(path):
        if len(tok) < ncols:
            raise SequenceError(f"{where}: expected '{what}', got {len(tok)} fields")
        yield where, tok


def _float(s: str, where: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise SequenceError(f"{where}: malformed number {s!r}") from None
    if not np.isfinite(v):
        raise SequenceError(f"{where}: non-finite value {s!r}")
    return v


def freiburg_id(root: Path) -> str | None:
    r = root.resolve()
    for part in (r.name, r.parent.name):
        m = re.search(r"freiburg([123])", part, re.IGNORECASE)
        if m:
            return m.group(1)
    return None


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    rgb_path, gt_path = root / "rgb.txt", root / "groundtruth.txt"
    for f in (rgb_path, gt_path):
        if not f.is_file():
            raise SequenceError(f"not a TUM RGB-D sequence: no {f.name} in {root}")
    rgb = [(_float(t[0], w), t[1]) for w, t in _rows(rgb_path, 2, "timestamp filename")]
    gt_t, gt_pose = [], []
    for where, t in _rows(gt_path, 8, "timestamp tx ty tz qx qy qz qw"):
        v = [_float(x, where) for x in t[:8]]
        gt_t.append(v[0])
        gt_pose.append(pose_from_quat_t(checked_quaternion(v[4:8], where), v[1:4]))
    if not rgb:
        raise SequenceError(f"{rgb_path} lists no images")
    if not gt_t:
        raise SequenceError(f"{gt_path} has no poses")

    order = np.argsort(gt_t, kind="stable")
    ts = np.asarray(gt_t)[order]
    frames, seen, dropped = [], set(), 0
    for t, rel in rgb:
        i = int(np.searchsorted(ts, t))
        cands = [j for j in (i - 1, i) if 0 <= j < len(ts)]
        j = min(cands, key=lambda j: abs(ts[j] - t))
        if abs(ts[j] - t) > MAX_DT:
            dropped += 1
            continue
        path = root / rel
        name = posix_relpath(path, root)
        if name in seen:
            raise SequenceError(f"{rgb_path}: image {name} listed twice")
        seen.add(name)
        frames.append(Frame(name, path, 0, inverse(gt_pose[order[j]])))
    if not frames:
        raise SequenceError(f"no image of {rgb_path} has a groundtruth pose within {MAX_DT} s")

    size = image_size(frames[0].image_path)
    cam_file = root / "camera.txt"
    if cam_file.is_file():
        camera = fit_camera(read_single_camera_text(cam_file), size)
        source = str(cam_file.name)
    else:
        fid = freiburg_id(root)
        camera = fit_camera(DEFAULT_CAMERAS[fid], size)
        source = f"freiburg{fid}" if fid else "ros-default"
    return Sequence(root, NAME, {0: camera}, frames, {"unassociated": dropped, "intrinsics": source})
