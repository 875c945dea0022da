"""Microsoft 7-Scenes (and the same layout of 12-Scenes-like captures).

::

    SCENE/                         (or a single sequence folder, e.g. seq-XX, as the root)
      seq-01/frame-000000.color.png  (or .jpg)
      seq-01/frame-000000.pose.txt   4x4 camera-to-world (world_from_cam), OpenCV camera axes
      ...
      TrainSplit.txt, TestSplit.txt  optional, lines ``sequence1`` -> seq-01
      camera.txt | intrinsics.txt    optional: a 3x3 K (9 numbers), or one COLMAP camera line

Intrinsics: PINHOLE fx = fy = 525, cx = 320, cy = 240 for 640x480 (the RGB camera's focal, as DSAC*,
ACE and hloc use it; the 585 px that 7-Scenes publishes is the depth camera's), unless a ``camera.txt`` /
``intrinsics.txt`` is present. The image size is read from the first colour image;
a default (or COLMAP-line) camera of another size is rescaled to it.

Every colour image needs its pose file and every pose file its colour image (SequenceError
otherwise). Rule for invalid poses: a pose file whose numbers include inf/nan (the original
7-Scenes data has a few such frames) is *skipped*: the frame is left out and listed in
``Sequence.extra["skipped"]``, and a warning is logged. Any other malformed pose file (not 16
numbers, not a rigid transform) is a SequenceError, and so is a sequence where every frame is
skipped. When split files exist, ``extra["split"]`` gives "train"/"test" per frame ("other" for
sequences listed in neither).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import inverse
from ..types import Camera, Frame, Sequence
from .common import (
    checked_pose,
    fit_camera,
    guarded,
    image_size,
    make_camera,
    posix_relpath,
    read_single_camera_text,
    read_text,
)

NAME = "7scenes"
DEFAULT_CAMERA = Camera("PINHOLE", 640, 480, [525.0, 525.0, 320.0, 240.0])
CAMERA_FILES = ("camera.txt", "intrinsics.txt")
_COLOR_RE = re.compile(r"^(frame-\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_POSE_RE = re.compile(r"^(frame-\d+)\.pose\.txt$")
_SEQ_RE = re.compile(r"^seq-?(\d+)$")
_MSVC_NONFINITE = re.compile(r"^[-+]?1\.#(INF|IND|QNAN|SNAN)[\w.+-]*$", re.IGNORECASE)  # "-1.#IND000e+000"
log = logging.getLogger(__name__)


def _has_poses(d: Path) -> bool:
    return next(d.glob("frame-*.pose.txt"), None) is not None


def _seq_dirs(root: Path) -> list[Path]:
    if _has_poses(root):  # the root is a single sequence
        return [root]
    return sorted(d for d in root.glob("seq-*") if d.is_dir() and _SEQ_RE.match(d.name) and _has_poses(d))


def detect(root: Path) -> bool:
    root = Path(root)
    if _has_poses(root):
        return True
    return any(d.is_dir() and _SEQ_RE.match(d.name) and _has_poses(d) for d in root.glob("seq-*"))


def _read_pose(path: Path) -> np.ndarray | None:
    """world_from_cam of a pose file; None when it holds inf/nan (skipped by the caller)."""
    text = read_text(path, "pose file")
    try:
        vals = [float(_MSVC_NONFINITE.sub("nan", x)) for x in text.split()]
    except ValueError as e:
        raise SequenceError(f"pose file {path} is not 16 numbers ({e})") from None
    if len(vals) != 16:
        raise SequenceError(f"pose file {path} has {len(vals)} numbers; expected a 4x4 matrix (16)")
    T = np.array(vals).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return None
    return checked_pose(T, f"pose file {path}")


def _read_K_file(path: Path, size: tuple[int, int]) -> Camera:
    text = read_text(path, "camera file")
    body = " ".join(line.split("#", 1)[0] for line in text.splitlines()).split()
    try:
        vals = [float(x) for x in body]
    except ValueError:
        vals = None
    if vals is None:  # not a bare K: a COLMAP camera line
        return fit_camera(read_single_camera_text(path), size)
    if len(vals) != 9:
        raise SequenceError(f"{path}: expected a 3x3 intrinsic matrix K (9 numbers), got {len(vals)} numbers")
    K = np.array(vals).reshape(3, 3)
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise SequenceError(f"{path}: K must be [[fx 0 cx] [0 fy cy] [0 0 1]]")
    return make_camera("PINHOLE", size[0], size[1], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], str(path))


def _read_split(path: Path) -> set[int]:
    lines = read_text(path, "split file").split()
    out = set()
    for tok in lines:
        m = re.fullmatch(r"(?:sequence|seq-?)(\d+)", tok.strip(), re.IGNORECASE)
        if not m:
            raise SequenceError(f"{path}: unexpected line {tok!r} (expected 'sequenceN')")
        out.add(int(m.group(1)))
    return out


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    seqs = _seq_dirs(root)
    if not seqs:
        raise SequenceError(f"no 7-Scenes sequence (seq-XX/frame-NNNNNN.pose.txt) in {root}")

    items = []  # (seq number, image path, pose path)
    for d in seqs:
        colors, poses = {}, {}
        for p in d.iterdir():
            m = _COLOR_RE.match(p.name)
            if m:
                if m.group(1) in colors:
                    raise SequenceError(f"{d}: two colour images for {m.group(1)}")
                colors[m.group(1)] = p
            m = _POSE_RE.match(p.name)
            if m:
                poses[m.group(1)] = p
        for stem in sorted(colors.keys() | poses.keys()):
            if stem not in poses:
                raise SequenceError(f"missing pose file {d / (stem + '.pose.txt')} for image {colors[stem]}")
            if stem not in colors:
                raise SequenceError(f"missing colour image {d / (stem + '.color.png')} for pose file {poses[stem]}")
            m = _SEQ_RE.match(d.name)
            items.append((int(m.group(1)) if m else 0, colors[stem], poses[stem]))

    size = image_size(items[0][1])
    cam_file = next((root / f for f in CAMERA_FILES if (root / f).is_file()), None)
    camera = _read_K_file(cam_file, size) if cam_file else fit_camera(DEFAULT_CAMERA, size)

    train_f, test_f = root / "TrainSplit.txt", root / "TestSplit.txt"
    train = _read_split(train_f) if train_f.is_file() else None
    test = _read_split(test_f) if test_f.is_file() else None

    frames, split, skipped = [], [], []
    for seq_no, img, pose in items:
        world_from_cam = _read_pose(pose)
        name = posix_relpath(img, root)
        if world_from_cam is None:
            skipped.append(name)
            continue
        frames.append(Frame(name, img, 0, inverse(world_from_cam)))
        split.append("train" if train and seq_no in train else "test" if test and seq_no in test else "other")
    if skipped:
        log.warning(
            "7scenes: skipped %d frame(s) of %s whose pose has inf/nan, e.g. %s", len(skipped), root, skipped[0]
        )
    if not frames:
        raise SequenceError(f"every pose file of {root} has inf/nan values; no usable frame")
    extra = {"skipped": skipped}
    if train is not None or test is not None:
        extra["split"] = split
    return Sequence(root, NAME, {0: camera}, frames, extra)


def write(seq: Sequence, root: Path) -> list[Path]:
    """Write ``frame-*.pose.txt`` next to each image and ``camera.txt`` (3x3 K; a COLMAP camera
    line for a camera with distortion) for a sequence whose images already lie under ``root``
    with 7-Scenes names (``seq-XX/frame-NNNNNN.color.png`` or ``frame-NNNNNN.color.png``)."""
    root = Path(root)
    if len({f.camera_id for f in seq.frames}) != 1:
        raise SequenceError("a 7-Scenes sequence has exactly one camera")
    cam = seq.cameras[seq.frames[0].camera_id]
    written = []
    for f in seq.frames:
        p = root / f.name
        m = _COLOR_RE.match(p.name)
        if not m:
            raise SequenceError(f"image name {f.name} does not follow 7-Scenes naming (frame-NNNNNN.color.png)")
        pose_path = p.with_name(m.group(1) + ".pose.txt")
        wfc = inverse(f.cam_from_world)
        pose_path.write_text("".join("\t".join(repr(float(v)) for v in row) + "\n" for row in wfc))
        written.append(pose_path)
    cam_path = root / "camera.txt"
    if cam.is_pinhole:
        cam_path.write_text("".join(" ".join(repr(float(v)) for v in row) + "\n" for row in cam.K))
    else:
        cam_path.write_text(
            f"1 {cam.model} {cam.width} {cam.height} " + " ".join(repr(float(v)) for v in cam.params) + "\n"
        )
    written.append(cam_path)
    return written
