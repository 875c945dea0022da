"""NeRF / instant-ngp ``transforms.json``.

::

    SEQ/
      transforms.json                      (instant-ngp, nerfstudio-like: all frames)
      | transforms_train.json, transforms_val.json, transforms_test.json   (Blender-style splits)
      images/...                           (``file_path`` is relative to SEQ)

When ``transforms.json`` exists it is the only file read. Otherwise every split file present is
read (train, val, test order) and ``Sequence.extra["split"]`` lists the split of each frame.

Poses: ``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, z backward);
it is converted with :func:`geometry.world_from_cam_opengl_to_opencv` and inverted. A 3x4 matrix
is accepted. The rotation must be orthonormal (scaled matrices are rejected).

Intrinsics (top level, each overridable per frame as instant-ngp allows):
``fl_x``/``fl_y`` (else ``camera_angle_x``/``camera_angle_y`` with ``f = w / 2 / tan(angle / 2)``;
a missing ``fl_y`` equals ``fl_x``), ``cx``/``cy`` (default ``w/2``, ``h/2``, taken as COLMAP
pixel coordinates, as instant-ngp's colmap2nerf writes them), ``w``/``h`` (else the size of the
first image), distortion ``k1 k2 p1 p2`` -> OPENCV, with ``k3`` -> FULL_OPENCV, all zero ->
PINHOLE. Fisheye cameras (``camera_model: OPENCV_FISHEYE`` as nerfstudio writes it, or instant-ngp's
``is_fisheye: true``) -> OPENCV_FISHEYE with ``k1 k2 k3 k4`` (equidistant model; they need
``fl_x``, as ``camera_angle_x`` describes a pinhole). ``k4`` on a perspective camera is not
supported. Frames with equal intrinsics share a camera id (0, 1, ... in order of appearance).

``file_path`` may lack its extension (Blender: ``./train/r_0``): ``.png``, ``.jpg``, ``.jpeg``
are tried.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ...errors import SequenceError
from ...geometry import inverse, world_from_cam_opencv_to_opengl, world_from_cam_opengl_to_opencv
from ..types import Camera, Frame, Sequence
from .common import checked_pose, guarded, image_size, make_camera, posix_relpath

NAME = "nerf"
FILENAME = "transforms.json"
DESCRIPTOR_FILES = (FILENAME, "transforms_*.json")
SPLITS = ("train", "val", "test")
_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "camera_angle_x",
    "camera_angle_y",
    "cx",
    "cy",
    "w",
    "h",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
    "is_fisheye",
    "camera_model",
)


def split_files(root: Path) -> list[tuple[str, Path]]:
    """The Blender-style split files (split name, path) present in ``root``, in SPLITS order."""
    return [(s, root / f"transforms_{s}.json") for s in SPLITS if (root / f"transforms_{s}.json").is_file()]


def detect(root: Path) -> bool:
    root = Path(root)
    return (root / FILENAME).is_file() or bool(split_files(root))


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SequenceError(f"cannot parse {path}: {e}") from None
    if not isinstance(data, dict):
        raise SequenceError(f"{path}: expected a JSON object at the top level")
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise SequenceError(f"{path}: missing 'frames' list")
    if not frames:
        raise SequenceError(f"{path}: the 'frames' list is empty")
    return data


def _resolve_image(root: Path, file_path: str) -> Path:
    p = root / file_path
    if p.is_file() or p.suffix.lower() in (".png", ".jpg", ".jpeg"):
        return p
    for ext in _EXTS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    return p


def _num(d: dict, key: str, where: str) -> float | None:
    v = d.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SequenceError(f"{where}: '{key}' must be a number, got {v!r}")
    if not math.isfinite(v):
        raise SequenceError(f"{where}: '{key}' is not finite ({v})")
    return float(v)


def _camera(d: dict, where: str, first_image_size) -> Camera:
    """Camera from the merged (top level + frame) intrinsics dict ``d``."""
    named = str(d.get("camera_model") or "OPENCV").upper()
    if named not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "OPENCV_FISHEYE"):
        raise SequenceError(
            f"{where}: unsupported camera model {d.get('camera_model')!r} "
            "(supported: OPENCV, PINHOLE, SIMPLE_PINHOLE, OPENCV_FISHEYE)"
        )
    fisheye = named == "OPENCV_FISHEYE" or bool(d.get("is_fisheye"))
    if fisheye and _num(d, "fl_x", where) is None and _num(d, "fl_y", where) is None:
        raise SequenceError(f"{where}: a fisheye camera needs fl_x (camera_angle_x describes a pinhole)")
    w, h = _num(d, "w", where), _num(d, "h", where)
    if w is None or h is None:
        w, h = first_image_size()
    fx, fy = _num(d, "fl_x", where), _num(d, "fl_y", where)
    ax, ay = _num(d, "camera_angle_x", where), _num(d, "camera_angle_y", where)
    if fx is None and ax is not None:
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None and ay is not None and _num(d, "fl_x", where) is None:
        fy = 0.5 * h / math.tan(0.5 * ay)
    if fx is None:
        fx = fy
    if fy is None:
        fy = fx
    if fx is None:
        raise SequenceError(f"{where}: no focal length (need fl_x or camera_angle_x)")
    cx, cy = _num(d, "cx", where), _num(d, "cy", where)
    cx = w / 2 if cx is None else cx
    cy = h / 2 if cy is None else cy
    k1, k2, k3, k4, p1, p2 = (_num(d, k, where) or 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    if fisheye:
        if p1 or p2:
            raise SequenceError(f"{where}: a fisheye camera has no tangential distortion (p1, p2)")
        return make_camera("OPENCV_FISHEYE", w, h, [fx, fy, cx, cy, k1, k2, k3, k4], where)
    if k4:
        raise SequenceError(f"{where}: distortion coefficient k4 is not supported")
    if k3:
        model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0, 0, 0]
    elif k1 or k2 or p1 or p2:
        model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    else:
        model, params = "PINHOLE", [fx, fy, cx, cy]
    return make_camera(model, w, h, params, where)


def _read_file(root: Path, path: Path, cameras: dict, cam_ids: dict, frames: list, seen: dict) -> None:
    data = _load_json(path)
    top = {k: data[k] for k in _INTRINSIC_KEYS if k in data}
    size_cache: list = []

    def first_image_size():
        if not size_cache:
            fp = data["frames"][0].get("file_path") if isinstance(data["frames"][0], dict) else None
            if not isinstance(fp, str):
                raise SequenceError(f"{path}: no w/h given and the first frame has no file_path")
            size_cache.append(image_size(_resolve_image(root, fp)))
        return size_cache[0]

    for i, fr in enumerate(data["frames"]):
        where = f"{path}: frame {i}"
        if not isinstance(fr, dict):
            raise SequenceError(f"{where} is not an object")
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise SequenceError(f"{where} has no file_path")
        where = f"{path}: frame {i} ({fp})"
        if "transform_matrix" not in fr:
            raise SequenceError(f"{where} has no transform_matrix")
        world_from_cam_gl = checked_pose(fr["transform_matrix"], where)
        cam_from_world = inverse(world_from_cam_opengl_to_opencv(world_from_cam_gl))

        own = {k: fr[k] for k in _INTRINSIC_KEYS if k in fr}
        if own and ("fl_x" in own or "camera_angle_x" in own):
            # a frame's own focal replaces the top-level focal / field of view entirely
            base = {k: v for k, v in top.items() if k not in ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y")}
        else:
            base = top
        cam = _camera({**base, **own}, where if own else str(path), first_image_size)
        key = (cam.model, cam.width, cam.height, tuple(cam.params.tolist()))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids)
            cameras[cam_ids[key]] = cam

        image_path = _resolve_image(root, fp)
        name = posix_relpath(image_path, root)
        if name in seen:
            raise SequenceError(f"{where}: image {name} listed twice (also in {seen[name]})")
        seen[name] = where
        frames.append(Frame(name, image_path, cam_ids[key], cam_from_world))


@guarded
def read(root: Path) -> Sequence:
    root = Path(root)
    if (root / FILENAME).is_file():
        files = [(None, root / FILENAME)]
    else:
        files = split_files(root)
        if not files:
            raise SequenceError(f"no {FILENAME} (or transforms_train/val/test.json) in {root}")
    cameras: dict[int, Camera] = {}
    cam_ids: dict = {}
    frames: list[Frame] = []
    seen: dict = {}
    split: list[str] = []
    for s, path in files:
        n = len(frames)
        try:
            _read_file(root, path, cameras, cam_ids, frames, seen)
        except SequenceError:
            raise
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise SequenceError(f"{path}: malformed file ({type(e).__name__}: {e})") from None
        split += [s] * (len(frames) - n)
    extra = {"split": split} if files[0][0] is not None else {}
    return Sequence(root, NAME, cameras, frames, extra)


def _intrinsics(cam: Camera) -> dict:
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    if cam.model == "FOV":
        raise SequenceError(f"camera model FOV cannot be written to {FILENAME}")
    if cam.is_fisheye:  # SIMPLE_RADIAL_FISHEYE / RADIAL_FISHEYE are OPENCV_FISHEYE with fewer terms
        d = {"camera_model": "OPENCV_FISHEYE", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
        d.update(w=int(cam.width), h=int(cam.height))
        d.update({k: float(v) for k, v in zip(("k1", "k2", "k3", "k4"), cam.opencv_distortion())})
        return d
    d = {
        "camera_angle_x": 2 * math.atan(cam.width / (2 * fx)),
        "camera_angle_y": 2 * math.atan(cam.height / (2 * fy)),
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": int(cam.width),
        "h": int(cam.height),
    }
    dist = cam.opencv_distortion()
    if np.any(dist[5:] != 0):
        raise SequenceError(f"camera model {cam.model} with k4..k6 cannot be written to {FILENAME}")
    for k, v in zip(("k1", "k2", "p1", "p2", "k3"), dist):
        if v != 0:
            d[k] = float(v)
    return d


def write(seq: Sequence, root: Path) -> Path:
    """Write ``transforms.json`` for a sequence whose images already lie under ``root``.

    One camera -> top-level intrinsics; several -> per-frame intrinsics. SIMPLE_RADIAL/RADIAL
    cameras come back as OPENCV, SIMPLE_RADIAL_FISHEYE/RADIAL_FISHEYE as OPENCV_FISHEYE (same
    distortion); FOV cameras cannot be written."""
    root = Path(root)
    data: dict = {}
    per_frame = len({f.camera_id for f in seq.frames}) > 1
    if not per_frame and seq.frames:
        data.update(_intrinsics(seq.cameras[seq.frames[0].camera_id]))
    frames = []
    for f in seq.frames:
        gl = world_from_cam_opencv_to_opengl(inverse(f.cam_from_world))
        fr = {"file_path": f.name, "transform_matrix": gl.tolist()}
        if per_frame:
            fr.update(_intrinsics(seq.cameras[f.camera_id]))
        frames.append(fr)
    data["frames"] = frames
    path = root / FILENAME
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
    return path
