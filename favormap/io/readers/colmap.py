"""COLMAP sparse models (binary or text), read with ``pycolmap.Reconstruction``.

::

    SEQ/
      sparse/0/ | sparse/ | colmap/sparse/0/ | SEQ itself
          cameras.bin|txt, images.bin|txt, (rigs, frames, points3D)
      images/...            (the images; image names are relative to this folder)

The first of those folders that holds both a cameras and an images file is the model. Only
registered images (with a pose) become frames; ``Frame.name`` is the image path relative to
SEQ (``images/<colmap name>``, or ``<colmap name>`` when the images lie directly in SEQ).
Camera models are taken 1:1 and must be one of ``types.SUPPORTED_MODELS``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import from_rigid3d
from ..types import SUPPORTED_MODELS, Camera, Frame, Sequence
from .common import checked_pose, guarded, make_camera, posix_relpath

NAME = "colmap"
MODEL_DIRS = ("sparse/0", "sparse", "colmap/sparse/0", ".")


# -- the reader ----------------------------------------------------------------------------------
def _has_model(d: Path) -> bool:
    return any((d / f"cameras.{e}").is_file() for e in ("bin", "txt")) and any(
        (d / f"images.{e}").is_file() for e in ("bin", "txt")
    )


def find_model(root: Path) -> Path | None:
    for sub in MODEL_DIRS:
        d = root / sub if sub != "." else root
        if _has_model(d):
            return d
    return None


def detect(root: Path) -> bool:
    return find_model(Path(root)) is not None


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    model_dir = find_model(root)
    if model_dir is None:
        raise SequenceError(
            f"no COLMAP model (cameras.bin/txt + images.bin/txt) in {root} (looked in {', '.join(MODEL_DIRS)})"
        )
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap reports parse failures as ValueError/RuntimeError
        raise SequenceError(f"cannot read the COLMAP model in {model_dir}: {e}") from None

    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise SequenceError(f"the COLMAP model in {model_dir} has no registered images")

    # where do the image names resolve? images/ (COLMAP's default) or the root itself
    image_dir = root / "images" if (root / "images").is_dir() else root
    for cand in (root / "images", root):
        if (cand / images[0].name).is_file():
            image_dir = cand
            break

    cameras: dict[int, Camera] = {}
    frames = []
    for im in images:
        cid = int(im.camera_id)
        if cid not in cameras:
            if cid not in rec.cameras:
                raise SequenceError(f"{model_dir}: image {im.name} refers to unknown camera {cid}")
            c = rec.cameras[cid]
            model = c.model.name
            if model not in SUPPORTED_MODELS:
                raise SequenceError(
                    f"{model_dir}: camera {cid} has unsupported model {model} "
                    f"(supported: {', '.join(SUPPORTED_MODELS)})"
                )
            cameras[cid] = make_camera(model, c.width, c.height, np.array(c.params), f"{model_dir}: camera {cid}")
        T = checked_pose(from_rigid3d(im.cam_from_world()), f"{model_dir}: image {im.name}")
        path = image_dir / im.name
        frames.append(Frame(posix_relpath(path, root), path, cid, T))
    return Sequence(root, NAME, cameras, frames, {"model_dir": posix_relpath(model_dir, root)})
