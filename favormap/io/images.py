"""Image loading: read, undistort to the pinhole model, resize. Build and localize share it, so a
query image goes through exactly the same steps as the mapping images.

The pinhole working camera of a camera (:func:`working_camera`; docs/cameras.md):

- pinhole models: the camera itself;
- perspective distortion models (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV): the pinhole with the
  camera's own focal length and principal point;
- fisheye models (SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, OPENCV_FISHEYE, FOV), and any distorted
  camera with a ``working_fov``: square pixels, the principal point at the image centre, the
  optical axis of the camera, and the horizontal field of view ``working_fov``, or by default the
  widest one (at most ``DEFAULT_MAX_FOV``) whose every pixel sees inside the original image (no
  border without image content).

Always at the original image size, then resized so that its longest side is ``max_side``.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from .types import Camera

# the widest horizontal field of view (degrees) the default rule gives a fisheye camera: wider pinholes
# stretch the periphery and shrink the centre of the image
DEFAULT_MAX_FOV = 120.0


def _border_points(width: int, height: int, n: int = 64) -> np.ndarray:
    """(4n, 2) points along the border of a ``width`` x ``height`` image (its outer edges)."""
    u, v = np.linspace(0, width, n), np.linspace(0, height, n)
    return np.concatenate(
        [np.c_[u, np.zeros(n)], np.c_[u, np.full(n, height)], np.c_[np.zeros(n), v], np.c_[np.full(n, width), v]]
    )


def _sees_inside(camera: Camera, K: np.ndarray, pixels: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether the rays of the pinhole ``K`` through ``pixels`` all hit ``camera``'s image."""
    xy = (pixels - K[:2, 2]) / [K[0, 0], K[1, 1]]
    uv = camera.to_pycolmap().img_from_cam(np.c_[xy, np.ones(len(xy))])
    return bool(
        np.all(np.isfinite(uv))
        and np.all(uv >= -tol)
        and np.all(uv[:, 0] <= camera.width + tol)
        and np.all(uv[:, 1] <= camera.height + tol)
    )


def _pinhole(width: int, height: int, fov_deg: float) -> Camera:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Camera("PINHOLE", width, height, [f, f, width / 2, height / 2])


@functools.lru_cache(maxsize=32)
def _wide_working_camera(model: str, width: int, height: int, params: tuple, fov: float | None) -> Camera:
    cam = Camera(model, width, height, np.array(params))
    if fov is not None:
        return _pinhole(width, height, fov)
    border = _border_points(width, height)
    if _sees_inside(cam, _pinhole(width, height, DEFAULT_MAX_FOV).K, border):
        return _pinhole(width, height, DEFAULT_MAX_FOV)
    lo, hi = 0.0, DEFAULT_MAX_FOV  # bisection on the field of view: inside at lo, outside at hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _sees_inside(cam, _pinhole(width, height, mid).K, border) else (lo, mid)
    if lo <= 0:
        from ..errors import InputError

        raise InputError(f"camera {model} {width}x{height} {list(params)}: no pinhole view lies inside its image")
    return _pinhole(width, height, lo)


def full_working_camera(camera: Camera) -> Camera:
    """The pinhole working camera of ``camera`` at the original image size (see the module's docstring)."""
    if camera.is_fisheye or (camera.working_fov is not None and not camera.is_pinhole):
        c = _wide_working_camera(
            camera.model, camera.width, camera.height, tuple(camera.params.tolist()), camera.working_fov
        )
        return Camera(c.model, c.width, c.height, c.params.copy())
    return camera.pinhole()


def working_camera(camera: Camera, max_side: int | None) -> Camera:
    """The pinhole camera that images of ``camera`` have after :func:`load_image`."""
    cam = full_working_camera(camera)
    if max_side and max(camera.width, camera.height) > max_side:
        s = max_side / max(camera.width, camera.height)
        cam = cam.scaled(max(1, round(camera.width * s)), max(1, round(camera.height * s)))
    return cam


def truncation(data: bytes) -> str | None:
    """Why an encoded JPEG or PNG is incomplete (None when it is complete or another format).
    Decoders fill a truncated image with grey and only warn, so this is checked before decoding."""
    if data[:2] == b"\xff\xd8":  # JPEG: must end with the EOI marker (trailing padding allowed)
        if b"\xff\xd9" not in data[-4096:].rstrip(b"\x00\xff\n\r "):
            return "truncated JPEG (no end-of-image marker)"
    elif data[:8] == b"\x89PNG\r\n\x1a\n":
        if b"IEND" not in data[-64:]:
            return "truncated PNG (no IEND chunk)"
    return None


def imread(path: Path, flags: int = cv2.IMREAD_COLOR, error: type[InputError] = InputError) -> np.ndarray:
    """Decode an image file, with one clear ``error`` naming the file when it is missing,
    unreadable, truncated or not an image (no decoder warning reaches the terminal)."""
    return decode_image(read_image_bytes(path, error), path, flags, error)


def read_image_bytes(path: Path, error: type[InputError] = InputError) -> bytes:
    """The undecoded bytes of an image file (one clear ``error`` when missing or unreadable)."""
    path = Path(path)
    if not path.is_file():
        raise error(f"image not found: {path}")
    try:
        return path.read_bytes()
    except OSError as e:
        raise error(f"cannot read image {path}: {e.strerror or e}") from None


def decode_image(data: bytes, name, flags: int = cv2.IMREAD_COLOR, error: type[InputError] = InputError) -> np.ndarray:
    """Decode the bytes of an image file (``name`` only for the error message)."""
    why = truncation(data)
    if why:
        raise error(f"cannot read image {name}: {why}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if img is None:
        raise error(f"cannot read image {name}: not a readable image file")
    return img


def read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(imread(path), cv2.COLOR_BGR2RGB)


def load_image(path: Path, camera: Camera, max_side: int | None = 640) -> tuple[np.ndarray, Camera]:
    """Read an image taken with ``camera``; return it undistorted and resized (RGB uint8) together
    with its pinhole working camera."""
    return decode_and_prepare(None, path, camera, max_side)


def decode_and_prepare(
    data: bytes | None, name, camera: Camera, max_side: int | None = 640
) -> tuple[np.ndarray, Camera]:
    """:func:`load_image` of an image file's bytes (``data``; None: read the file ``name``)."""
    img = read_rgb(name) if data is None else cv2.cvtColor(decode_image(data, name), cv2.COLOR_BGR2RGB)
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"image {name} is {w}x{h} but its camera is {camera.width}x{camera.height}")
    return prepare_image(img, camera, max_side)


@functools.lru_cache(maxsize=8)
def _undistort_maps(model: str, width: int, height: int, params: tuple, K: tuple) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (OpenCV pixel convention) from the pinhole ``K`` (same size) into the image of
    the camera: each working pixel's ray projected by pycolmap's camera model."""
    cam = Camera(model, width, height, np.array(params)).to_pycolmap()
    K = np.array(K).reshape(3, 3)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.c_[(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1], np.ones(u.size)]
    uv = cam.img_from_cam(rays) - 0.5
    uv[~np.isfinite(uv)] = -10.0  # outside the image: the border value
    maps = uv[:, 0].reshape(height, width).astype(np.float32), uv[:, 1].reshape(height, width).astype(np.float32)
    for m in maps:
        m.flags.writeable = False
    return maps


def prepare_image(img: np.ndarray, camera: Camera, max_side: int | None = 640) -> tuple[np.ndarray, Camera]:
    """Undistort (to the working camera, :func:`working_camera`) and resize an in-memory RGB image."""
    out_cam = working_camera(camera, max_side)
    size = (out_cam.width, out_cam.height)
    if camera.is_fisheye or (camera.working_fov is not None and not camera.is_pinhole):
        # undistort at the source's own resolution (into the working camera at that size), then shrink:
        # towards its edges the pinhole working camera needs more pixels per radian than a fisheye image
        # resized to the working size still has, and remapping that one would blur the periphery
        full = full_working_camera(camera)
        mx, my = _undistort_maps(
            camera.model, camera.width, camera.height, tuple(camera.params.tolist()), tuple(full.K.ravel().tolist())
        )
        img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
        if size != (camera.width, camera.height):
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img), out_cam
    if size != (camera.width, camera.height):
        # resize first (cheaper), then undistort with the camera scaled to the new size
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        camera = camera.scaled(*size)
    if not camera.is_pinhole:
        dist = camera.opencv_distortion()
        if np.any(dist != 0):
            # OpenCV's pixel-centre convention is COLMAP's minus 0.5.
            K_cv = camera.K.copy()
            K_cv[0, 2] -= 0.5
            K_cv[1, 2] -= 0.5
            img = cv2.undistort(img, K_cv, dist, None, K_cv)
    return np.ascontiguousarray(img), out_cam


def prepare_query(image, camera: Camera, max_side: int | None = 640) -> tuple[np.ndarray, Camera]:
    """A query image (path, or RGB uint8 array at the camera's resolution or at another resolution
    with the same aspect ratio) -> (working image, pinhole working camera), through exactly the
    steps the mapping images went through."""
    img = read_rgb(image) if not isinstance(image, np.ndarray) else image
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"the query image must be an RGB uint8 array, got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    if (w, h) != (camera.width, camera.height):
        if (w, h) == (camera.height, camera.width):
            raise InputError(f"query image is {w}x{h} but the camera is {camera.width}x{camera.height} (rotated?)")
        if abs(w / h - camera.width / camera.height) > 0.01:
            raise InputError(f"query image is {w}x{h} but the camera is {camera.width}x{camera.height}; give --camera")
        camera = camera.scaled(w, h)  # same camera at another resolution
    return prepare_image(img, camera, max_side)


def sample_bilinear(img: np.ndarray, xy: np.ndarray, outside: float | None = None) -> np.ndarray:
    """Bilinear samples of a float32 image (H, W) or (H, W, C <= 4) at points ``xy`` (..., 2): (...) or
    (..., C), COLMAP pixel convention; outside the image the border pixels continue (``outside`` None) or
    the value ``outside`` (e.g. NaN) in every channel."""
    m = (xy.reshape(-1, 2) - 0.5).astype(np.float32)
    n, width = len(m), 4096  # cv2.remap's maps: fewer than 32,767 rows and columns
    m = np.concatenate([m, np.zeros((-n % width, 2), np.float32)]).reshape(-1, width, 2)
    border = (
        dict(borderMode=cv2.BORDER_REPLICATE)
        if outside is None
        else dict(borderMode=cv2.BORDER_CONSTANT, borderValue=(float(outside),) * 4)
    )
    out = cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, **border)
    channels = img.shape[2:]
    return out.reshape((-1,) + channels)[:n].reshape(xy.shape[:-1] + channels)


def patches_around(img: np.ndarray, xy: np.ndarray, radius: int) -> np.ndarray:
    """The (n, 2r+1, 2r+1) pixels of ``img`` around the points ``xy`` (n, 2; COLMAP convention), each
    centred on the pixel that holds its point (``floor(xy)``), mirrored beyond the image's edge as
    OpenCV's default border does (BORDER_REFLECT_101), so that a blur of a patch agrees with the blur
    of the whole image inside it."""
    r = int(radius)
    pad = np.pad(img, [(r, r), (r, r)] + [(0, 0)] * (img.ndim - 2), mode="reflect")
    c = np.floor(np.asarray(xy, np.float64)).astype(np.int64)
    h, w = img.shape[:2]
    c = np.clip(c, 0, [w - 1, h - 1])  # a keypoint on the very edge (x == w) is in the last pixel
    g = np.arange(2 * r + 1)
    return pad[c[:, 1, None, None] + g[None, :, None], c[:, 0, None, None] + g[None, None, :]]
