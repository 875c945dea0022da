"""Cambridge Landmarks (PoseNet).

::

    SCENE/
      dataset_train.txt, dataset_test.txt    (at least one)
      seq1/frame00001.png ...
      camera.txt | cameras.txt               optional: one camera in COLMAP text format

Each split file has 3 header lines, then ``path X Y Z W P Q R``: ``X Y Z`` is the camera centre in
world coordinates and ``W P Q R`` a unit quaternion (w, x, y, z) of the *cam_from_world* rotation
(PoseNet convention: it rotates world vectors into the camera frame; camera axes are OpenCV's). So
``R = quat(W, P, Q, R)`` and ``cam_from_world = [R | -R @ C]``.

Intrinsics are not part of the data set. Default: SIMPLE_PINHOLE with ``f = 0.87 * width`` (about
1670 px for the 1920x1080 originals) and the principal point at the image centre, the size read
from the first image. A ``camera.txt`` / ``cameras.txt`` with exactly one COLMAP camera replaces
it (rescaled when it was given for another image size). ``extra["split"]`` is "train"/"test" per
frame. Non-finite numbers or a zero quaternion are a SequenceError naming the file and line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import cam_from_world_from_center, quat_to_rotmat
from ..types import Frame, Sequence
from .common import (
    checked_quaternion,
    fit_camera,
    guarded,
    image_size,
    make_camera,
    posix_relpath,
    read_single_camera_text,
    read_text,
)

NAME = "cambridge"
SPLIT_FILES = (("train", "dataset_train.txt"), ("test", "dataset_test.txt"))
DESCRIPTOR_FILES = tuple(f for _, f in SPLIT_FILES)
CAMERA_FILES = ("camera.txt", "cameras.txt")
DEFAULT_FOCAL_RATIO = 0.87  # focal length / image width
HEADER_LINES = 3


def detect(root: Path) -> bool:
    root = Path(root)
    return any((root / f).is_file() for _, f in SPLIT_FILES)


def _parse(path: Path) -> list[tuple[str, np.ndarray, np.ndarray, str]]:
    lines = read_text(path).splitlines()
    out = []
    for lineno, line in enumerate(lines, 1):
        if lineno <= HEADER_LINES or not line.strip():
            continue
        tok = line.split()
        where = f"{path}:{lineno}"
        if len(tok) != 8:
            raise SequenceError(f"{where}: expected 'path X Y Z W P Q R', got {len(tok)} fields")
        try:
            vals = np.array([float(x) for x in tok[1:]])
        except ValueError as e:
            raise SequenceError(f"{where}: malformed number ({e})") from None
        if not np.all(np.isfinite(vals)):
            raise SequenceError(f"{where}: non-finite pose values for {tok[0]}")
        out.append((tok[0], vals[:3], checked_quaternion(vals[3:], f"{where} ({tok[0]})"), where))
    return out


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    present = [(s, root / f) for s, f in SPLIT_FILES if (root / f).is_file()]
    if not present:
        raise SequenceError(f"no dataset_train.txt / dataset_test.txt in {root}")
    entries = []
    for split, path in present:
        entries += [(split, *e) for e in _parse(path)]
    if not entries:
        raise SequenceError(f"{', '.join(str(p) for _, p in present)}: no images listed")

    size = image_size(root / entries[0][1])
    cam_file = next((root / f for f in CAMERA_FILES if (root / f).is_file()), None)
    if cam_file is not None:
        camera = fit_camera(read_single_camera_text(cam_file), size)
    else:
        w, h = size
        camera = make_camera("SIMPLE_PINHOLE", w, h, [DEFAULT_FOCAL_RATIO * w, w / 2, h / 2], "default camera")

    frames, split, seen = [], [], {}
    for s, rel, center, q_wxyz, where in entries:
        q_xyzw = np.array([q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]])
        T = cam_from_world_from_center(quat_to_rotmat(q_xyzw), center)
        path = root / rel
        name = posix_relpath(path, root)
        if name in seen:
            raise SequenceError(f"{where}: image {name} listed twice (also at {seen[name]})")
        seen[name] = where
        frames.append(Frame(name, path, 0, T))
        split.append(s)
    return Sequence(root, NAME, {0: camera}, frames, {"split": split})
