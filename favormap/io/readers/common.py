"""Helpers every sequence reader shares: the error guard, checked cameras and poses (one rotation
tolerance, near-rigid rotations projected onto SO(3) and reported once per read), COLMAP text
camera files, image sizes and relative paths."""

from __future__ import annotations

import functools
import logging
import os
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from ...errors import InputError, SequenceError
from ...geometry import ROTATION_TOL, nearest_rotation, quaternion_deviation, rotation_deviation
from ..types import SUPPORTED_MODELS, Camera

log = logging.getLogger("favormap.io")

# deviations of the rotations read by the reader that runs now: (deviation, where)
_ROTATIONS: ContextVar[list | None] = ContextVar("favormap_reader_rotations", default=None)
# below this a rotation is exact up to float rounding and not worth a word
_ROUNDING = 1e-9


def guarded(read):
    """Decorator for a reader's ``read``: any stray parse error becomes a SequenceError naming the
    root, and near-rigid rotations that were projected onto SO(3) are reported in one log line."""

    @functools.wraps(read)
    def wrapper(root):
        token = _ROTATIONS.set([])
        try:
            seq = read(root)
            report_rotations(_ROTATIONS.get(), f"{read.__module__.rsplit('.', 1)[-1]}: {root}")
            return seq
        except SequenceError:
            raise
        except (InputError, KeyError, IndexError, ValueError, TypeError, OSError, UnicodeDecodeError) as e:
            raise SequenceError(f"cannot read sequence {root}: {type(e).__name__}: {e}") from None
        finally:
            _ROTATIONS.reset(token)

    return wrapper


def report_rotations(devs: list | None, what: str) -> None:
    """One log line when some rotations were not exact: how many, the largest deviation, where."""
    if not devs:
        return
    projected = [d for d in devs if d[0] > _ROUNDING]
    if not projected:
        return
    worst, where = max(projected, key=lambda d: d[0])
    log.info(
        "%s: %d of %d rotations were not exactly orthonormal and were projected onto SO(3) "
        "(largest deviation |R^T R - I| = %.1e at %s; tolerance %.0e)",
        what,
        len(projected),
        len(devs),
        worst,
        where,
        ROTATION_TOL,
    )


def _record(dev: float, where: str) -> None:
    rec = _ROTATIONS.get()
    if rec is not None:
        rec.append((dev, where))


def checked_rotation(R, where: str) -> np.ndarray:
    """``R`` projected onto SO(3) when it deviates by at most ``ROTATION_TOL``; SequenceError otherwise."""
    dev = rotation_deviation(R)
    if not dev <= ROTATION_TOL:
        why = (
            "determinant <= 0 (a reflection or a degenerate matrix)"
            if dev == float("inf")
            else f"max |R^T R - I| = {dev:.1e}"
        )
        raise SequenceError(
            f"{where}: pose is not a rigid transform (rotation not orthonormal: {why}; tolerance {ROTATION_TOL:.0e})"
        )
    _record(dev, where)
    return nearest_rotation(R) if dev > 0 else np.asarray(R, dtype=np.float64)


def checked_quaternion(q, where: str) -> np.ndarray:
    """A quaternion normalised, when the rotation it stands for is within ``ROTATION_TOL`` (see
    :func:`geometry.quaternion_deviation`); SequenceError otherwise."""
    q = np.asarray(q, dtype=np.float64)
    dev = quaternion_deviation(q)
    if not dev <= ROTATION_TOL:
        n = np.linalg.norm(q)
        raise SequenceError(
            f"{where}: not a unit quaternion (norm {n:.6g}; the rotation deviates by {dev:.1e}, "
            f"tolerance {ROTATION_TOL:.0e})"
            if n > 1e-12
            else f"{where}: zero quaternion"
        )
    _record(dev, where)
    return q / np.linalg.norm(q)


def checked_pose(T, where: str) -> np.ndarray:
    """``T`` as a 4x4 float64 rigid transform (a 3x4 gets its last row), its rotation projected onto
    SO(3) (see :func:`checked_rotation`); SequenceError otherwise."""
    try:
        T = np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise SequenceError(f"{where}: pose is not a numeric matrix") from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise SequenceError(f"{where}: pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise SequenceError(f"{where}: pose has non-finite values (inf/nan)")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > ROTATION_TOL:
        raise SequenceError(f"{where}: pose is not a rigid transform (last row {T[3].tolist()}, expected 0 0 0 1)")
    T[:3, :3] = checked_rotation(T[:3, :3], where)
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


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


def read_text(path: Path, what: str = "file") -> str:
    """The text of a file a reader needs; SequenceError naming it when it cannot be read."""
    try:
        return Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SequenceError(f"cannot read {what} {path}: {e}") from None


def text_rows(path: Path, what: str = "file"):
    """``(where, tokens)`` of each non-empty line of a text file, ``#`` comments removed;
    ``where`` is ``path:lineno`` for error messages."""
    for lineno, line in enumerate(read_text(path, what).splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if line:
            yield f"{path}:{lineno}", line.split()


def read_cameras_text(path: Path) -> dict[int, Camera]:
    """Cameras of a COLMAP ``cameras.txt``-style file: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``
    per line (``#`` comments; the leading id may be left out, then lines count from 1)."""
    path = Path(path)
    cameras: dict[int, Camera] = {}
    for where, tok in text_rows(path, "camera file"):
        try:
            if tok[0].upper() in SUPPORTED_MODELS or not tok[0].lstrip("+-").isdigit():
                cam_id, tok = len(cameras) + 1, tok
            else:
                cam_id, tok = int(tok[0]), tok[1:]
            model = tok[0].upper()
            if model not in SUPPORTED_MODELS:
                raise SequenceError(
                    f"{where}: unsupported camera model {tok[0]!r} (supported: {', '.join(SUPPORTED_MODELS)})"
                )
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
    return Path(os.path.relpath(os.path.normpath(path), os.path.normpath(root))).as_posix()
