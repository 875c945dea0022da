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

This module also holds the small helpers the other readers share (COLMAP text camera files,
image sizes, checked camera/pose construction).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError, SequenceError
from ...geometry import from_rigid3d, is_rigid
from ..types import SUPPORTED_MODELS, Camera, Frame, Sequence

NAME = "colmap"
MODEL_DIRS = ("sparse/0", "sparse", "colmap/sparse/0", ".")


# -- helpers shared with the other readers ------------------------------------------------------
def guarded(read):
    """Decorator for a reader's ``read``: any stray parse error becomes a SequenceError naming the root."""
    import functools

    @functools.wraps(read)
    def wrapper(root):
        try:
            return read(root)
        except SequenceError:
            raise
        except (InputError, KeyError, IndexError, ValueError, TypeError, OSError, UnicodeDecodeError) as e:
            raise SequenceError(f"cannot read sequence {root}: {type(e).__name__}: {e}") from None

    return wrapper


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file; SequenceError when it is missing or unreadable."""
    import cv2

    from ..images import imread

    img = imread(path, cv2.IMREAD_UNCHANGED, SequenceError)
    return int(img.shape[1]), int(img.shape[0])


def make_camera(model: str, width, height, params, where: str) -> Camera:
    """A Camera, with every problem reported as a SequenceError that names ``where``."""
    try:
        w, h = float(width), float(height)
        if not (np.isfinite(w) and np.isfinite(h)) or w != int(w) or h != int(h):
            raise SequenceError(f"{where}: invalid image size {width}x{height}")
        params = np.asarray(params, dtype=np.float64)
        if not np.all(np.isfinite(params)):
            raise SequenceError(f"{where}: non-finite camera parameters {params.tolist()}")
        return Camera(str(model), int(w), int(h), params)
    except SequenceError:
        raise
    except (InputError, TypeError, ValueError) as e:
        raise SequenceError(f"{where}: invalid camera ({e})") from None


def checked_pose(T, where: str) -> np.ndarray:
    """``T`` as a 4x4 float64 rigid transform (a 3x4 gets its last row); SequenceError otherwise."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise SequenceError(f"{where}: pose is not a numeric matrix") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise SequenceError(f"{where}: pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise SequenceError(f"{where}: pose has non-finite values (inf/nan)")
    if not is_rigid(T):
        raise SequenceError(f"{where}: pose is not a rigid transform (rotation not orthonormal)")
    return T


def read_cameras_text(path: Path) -> dict[int, Camera]:
    """Cameras of a COLMAP ``cameras.txt``-style file: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``
    per line (``#`` comments; the leading id may be left out, then lines count from 1)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SequenceError(f"cannot read camera file {path}: {e}") from None
    cameras: dict[int, Camera] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        where = f"{path}:{lineno}"
        try:
            if tok[0].upper() in SUPPORTED_MODELS or not tok[0].lstrip("+-").isdigit():
                cam_id, tok = len(cameras) + 1, tok
            else:
                cam_id, tok = int(tok[0]), tok[1:]
            model = tok[0].upper()
            if model not in SUPPORTED_MODELS:
                raise SequenceError(f"{where}: unsupported camera model {tok[0]!r} "
                                    f"(supported: {', '.join(SUPPORTED_MODELS)})")
            width, height = float(tok[1]), float(tok[2])
            params = [float(x) for x in tok[3:]]
        except IndexError:
            raise SequenceError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'") from None
        except ValueError as e:
            raise SequenceError(f"{where}: malformed camera line ({e})") from None
        if cam_id in cameras:
            raise SequenceError(f"{where}: duplicate camera id {cam_id}")
        cameras[cam_id] = make_camera(model, width, height, params, where)
    if not cameras:
        raise SequenceError(f"camera file {path} contains no camera")
    return cameras


def read_single_camera_text(path: Path) -> Camera:
    cams = read_cameras_text(path)
    if len(cams) != 1:
        raise SequenceError(f"camera file {path} has {len(cams)} cameras; expected exactly one")
    return next(iter(cams.values()))


def fit_camera(camera: Camera, size: tuple[int, int]) -> Camera:
    """``camera`` rescaled to the actual image size (no-op when it already matches)."""
    if (camera.width, camera.height) == tuple(size):
        return camera
    return camera.scaled(int(size[0]), int(size[1]))


def posix_relpath(path: Path, root: Path) -> str:
    """``path`` relative to ``root`` as a normalised posix string (may start with ``..``)."""
    import os

    return Path(os.path.relpath(os.path.normpath(path), os.path.normpath(root))).as_posix()


# -- the reader ----------------------------------------------------------------------------------
def _has_model(d: Path) -> bool:
    return any((d / f"cameras.{e}").is_file() for e in ("bin", "txt")) and any(
        (d / f"images.{e}").is_file() for e in ("bin", "txt"))


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
        raise SequenceError(f"no COLMAP model (cameras.bin/txt + images.bin/txt) in {root} "
                            f"(looked in {', '.join(MODEL_DIRS)})")
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
                raise SequenceError(f"{model_dir}: camera {cid} has unsupported model {model} "
                                    f"(supported: {', '.join(SUPPORTED_MODELS)})")
            cameras[cid] = make_camera(model, c.width, c.height, np.array(c.params), f"{model_dir}: camera {cid}")
        T = checked_pose(from_rigid3d(im.cam_from_world()), f"{model_dir}: image {im.name}")
        path = image_dir / im.name
        frames.append(Frame(posix_relpath(path, root), path, cid, T))
    return Sequence(root, NAME, cameras, frames, {"model_dir": posix_relpath(model_dir, root)})
