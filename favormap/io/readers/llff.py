"""LLFF ``poses_bounds.npy`` scenes (the NeRF "real forward-facing" data).

::

    SCENE/
      poses_bounds.npy      N x 17 float: a 3x5 matrix [R | c | hwf] flattened row-major + near/far
      images/               N images; sorted file names (.png/.jpg/.jpeg) match the rows in order
      images_4/, images_8/  optional downsampled copies (used when images/ is absent: smallest factor)

Rotation columns are LLFF's [down, right, backwards] axes in world coordinates and ``c`` is the
camera centre; :func:`geometry.world_from_cam_llff_to_opencv` turns that into world_from_cam with
OpenCV columns [right, down, forward] = [c1, c0, -c2], which is then inverted.

Intrinsics: ``hwf`` = (height, width, focal) of the full-resolution images; the camera is
SIMPLE_PINHOLE ``[f, w/2, h/2]`` for ``w x h``, rescaled to the actual size of the first image of
the folder used (so images_4/ gets f/4). Rows with different hwf get different camera ids.
``extra["bounds"]`` holds the near/far depth bounds per frame, ``extra["images_dir"]`` the folder.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import inverse, world_from_cam_llff_to_opencv
from ..types import Camera, Frame, Sequence
from .common import checked_pose, guarded, image_size, make_camera, posix_relpath

NAME = "llff"
FILENAME = "poses_bounds.npy"
DESCRIPTOR_FILES = (FILENAME,)
_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def detect(root: Path) -> bool:
    return (Path(root) / FILENAME).is_file()


def _image_dir(root: Path) -> Path:
    if (root / "images").is_dir():
        return root / "images"
    cands = []
    for d in root.glob("images_*"):
        m = re.fullmatch(r"images_(\d+)", d.name)
        if m and d.is_dir():
            cands.append((int(m.group(1)), d))
    if not cands:
        raise SequenceError(f"no images/ (or images_N/) folder in {root}")
    return min(cands)[1]


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    path = root / FILENAME
    if not path.is_file():
        raise SequenceError(f"not an LLFF scene: no {FILENAME} in {root}")
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as e:  # np.load raises OSError, ValueError, EOFError, ... on broken files
        raise SequenceError(f"cannot read {path}: {type(e).__name__}: {e}") from None
    if (
        not isinstance(arr, np.ndarray)
        or arr.ndim != 2
        or arr.shape[1] != 17
        or not np.issubdtype(arr.dtype, np.number)
    ):
        raise SequenceError(f"{path}: expected an N x 17 numeric array, got {getattr(arr, 'shape', None)}")
    if arr.shape[0] == 0:
        raise SequenceError(f"{path}: no poses")
    arr = arr.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if bad.size:
        raise SequenceError(f"{path}: row {bad[0]} has non-finite values (inf/nan)")
    poses = arr[:, :15].reshape(-1, 3, 5)
    bounds = arr[:, 15:]

    image_dir = _image_dir(root)
    images = sorted(p for p in image_dir.iterdir() if p.suffix.lower() in _IMAGE_EXTS and p.is_file())
    if len(images) != len(poses):
        raise SequenceError(f"{path} has {len(poses)} poses but {image_dir} holds {len(images)} images")

    hwf = poses[:, :, 4]
    h0, w0 = hwf[0, 0], hwf[0, 1]
    if h0 <= 0 or w0 <= 0:
        raise SequenceError(f"{path}: invalid image size in hwf: {hwf[0].tolist()}")
    W, H = image_size(images[0])
    sx, sy = W / w0, H / h0

    cameras: dict[int, Camera] = {}
    cam_ids: dict = {}
    frames = []
    for i, (P, img) in enumerate(zip(poses, images)):
        h, w, f = (float(x) for x in P[:, 4])
        if (h, w, f) not in cam_ids:
            where = f"{path}: row {i}"
            if h <= 0 or w <= 0 or f <= 0 or h != round(h) or w != round(w):
                raise SequenceError(f"{where}: invalid hwf {[h, w, f]}")
            cam = make_camera("SIMPLE_PINHOLE", int(w), int(h), [f, w / 2, h / 2], where)
            new_w, new_h = max(1, round(w * sx)), max(1, round(h * sy))
            if (new_w, new_h) != (cam.width, cam.height):
                cam = cam.scaled(new_w, new_h)
            cam_ids[(h, w, f)] = len(cam_ids)
            cameras[cam_ids[(h, w, f)]] = cam
        wfc = checked_pose(world_from_cam_llff_to_opencv(P[:, :4]), f"{path}: row {i}")
        frames.append(Frame(posix_relpath(img, root), img, cam_ids[(h, w, f)], inverse(wfc)))
    extra = {"bounds": bounds.tolist(), "images_dir": posix_relpath(image_dir, root)}
    return Sequence(root, NAME, cameras, frames, extra)
