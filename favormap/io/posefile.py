"""Pose, transform and camera files given on the command line (query, localize, merge).

Pose files hold ``world_from_cam`` (camera-to-world, OpenCV camera axes; the 7-Scenes convention):

- a 4x4 matrix as whitespace-separated text (16 numbers; 12 numbers are read as the top 3x4 rows);
- or one TUM line ``tx ty tz qx qy qz qw`` (optionally preceded by a timestamp: 8 numbers).

Lines starting with ``#`` are comments. :func:`read_pose` returns ``cam_from_world`` (favormap's
convention everywhere else); :func:`write_pose` writes the 4x4 ``world_from_cam`` text form.

Transform files (``merge --transform``) hold a 4x4 (or 3x4) matrix that maps points of one map's
world into another's: a rigid transform, or a similarity (uniform scale times rotation).

Camera specs: a COLMAP ``cameras.txt`` line (``ID MODEL W H params...`` or ``MODEL W H params...``),
a JSON object ``{"model", "width", "height", "params"}``, or a file holding either (for a
cameras.txt file, its first camera).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import geometry
from ..errors import InputError
from .types import SUPPORTED_MODELS, Camera

_ROT_TOL = geometry.ROTATION_TOL  # the project's one rotation tolerance (text files carry few digits)


def _read_numbers(path: Path, what: str) -> tuple[np.ndarray, int]:
    """All numbers of a text file (comments skipped) and the number of non-empty lines."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{what} file not found: {path}")
    if path.is_dir():
        raise InputError(f"{what} file {path} is a directory")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read {what} file {path}: {e}") from None
    lines = [ln.split("#", 1)[0].replace(",", " ").strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    tokens = " ".join(lines).split()
    try:
        vals = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise InputError(f"{what} file {path}: not a number: {bad!r}") from None
    if not np.all(np.isfinite(vals)):
        raise InputError(f"{what} file {path} contains non-finite numbers (nan/inf)")
    return vals, len(lines)


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _matrix(vals: np.ndarray, path: Path, what: str) -> np.ndarray:
    T = np.eye(4)
    if len(vals) == 16:
        T[:] = vals.reshape(4, 4)
        if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
            raise InputError(f"{what} file {path}: the last row of the 4x4 matrix must be 0 0 0 1, got {T[3].tolist()}")
    else:
        T[:3] = vals.reshape(3, 4)
    return T


def parse_pose(vals: np.ndarray, n_lines: int = 1, source: str = "<pose>") -> np.ndarray:
    """world_from_cam 4x4 from 16/12 matrix numbers or 7/8 TUM numbers; raises InputError."""
    path = source
    vals = np.asarray(vals, np.float64).ravel()
    if not np.all(np.isfinite(vals)):
        raise InputError(f"pose file {path} contains non-finite numbers (nan/inf)")
    if len(vals) in (16, 12):
        T = _matrix(vals, path, "pose")
        dev = geometry.rotation_deviation(T[:3, :3])
        if not dev <= _ROT_TOL:
            raise InputError(
                f"pose file {path}: the rotation block is not a rotation (not orthonormal with det +1"
                + (f": max |R^T R - I| = {dev:.1e} > {_ROT_TOL:.0e})" if dev < float("inf") else ")")
            )
        T[:3, :3] = geometry.nearest_rotation(T[:3, :3])
        return T
    if len(vals) in (7, 8) and n_lines == 1:
        t, q = vals[-7:-4], vals[-4:]
        nq = np.linalg.norm(q)
        if not geometry.quaternion_deviation(q) <= _ROT_TOL:
            raise InputError(
                f"pose file {path}: the quaternion (qx qy qz qw) is not a unit quaternion (norm {nq:.6g}; "
                f"tolerance {_ROT_TOL / 4:.1e})"
            )
        return geometry.pose_from_quat_t(q / nq, t)
    raise InputError(
        f"pose file {path}: expected a 4x4 (16 numbers) or 3x4 (12) world_from_cam matrix, or one TUM line "
        f"'tx ty tz qx qy qz qw'; found {len(vals)} number(s) on {n_lines} line(s)"
    )


def read_world_from_cam(path) -> np.ndarray:
    vals, n_lines = _read_numbers(Path(path), "pose")
    return parse_pose(vals, n_lines, str(path))


def read_pose(path) -> np.ndarray:
    """cam_from_world (4x4, OpenCV axes) of a pose file holding world_from_cam."""
    return geometry.inverse(read_world_from_cam(path))


def write_pose(path, cam_from_world: np.ndarray) -> Path:
    """Write ``cam_from_world`` as a 4x4 world_from_cam text matrix (readable by :func:`read_pose`)."""
    T = np.asarray(cam_from_world, np.float64)
    if not geometry.is_rigid(T, tol=_ROT_TOL):
        raise InputError("write_pose: cam_from_world is not a rigid 4x4 transform")
    path = Path(path)
    np.savetxt(path, geometry.inverse(T), fmt="%.12g")
    return path


def format_pose_tum(cam_from_world: np.ndarray) -> str:
    """One TUM line ``tx ty tz qx qy qz qw`` of world_from_cam."""
    w = geometry.inverse(np.asarray(cam_from_world, np.float64))
    q = geometry.rotmat_to_quat(w[:3, :3])
    return " ".join(f"{v:.9g}" for v in np.r_[w[:3, 3], q])


def read_transform(path, allow_scale: bool = True) -> tuple[np.ndarray, float]:
    """A 4x4 transform file (rigid, or a similarity s*R|t with ``allow_scale``). Returns the 4x4
    matrix (rotation block cleaned up) and the scale ``s``."""
    path = Path(path)
    vals, n_lines = _read_numbers(path, "transform")
    if len(vals) not in (16, 12):
        raise InputError(
            f"transform file {path}: expected a 4x4 (16 numbers) or 3x4 (12 numbers) matrix, found {len(vals)} "
            "number(s)"
        )
    T = _matrix(vals, path, "transform")
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if det <= 0:
        raise InputError(f"transform file {path}: the 3x3 block is not a rotation (determinant {det:.4g} <= 0)")
    s = det ** (1 / 3)
    if not allow_scale and abs(s - 1) > _ROT_TOL:
        raise InputError(f"transform file {path}: expected a rigid transform, but it scales by {s:.6g}")
    R = A / s
    if not np.allclose(R.T @ R, np.eye(3), atol=_ROT_TOL):
        raise InputError(
            f"transform file {path}: not a rigid (or uniformly scaled) transform: the 3x3 block is not a scaled "
            "rotation"
        )
    T[:3, :3] = s * geometry.nearest_rotation(R)
    return T, s


# -- cameras ----------------------------------------------------------------------------------------
def _camera_from_tokens(tokens: list[str], source: str) -> Camera:
    if tokens and tokens[0].lstrip("-").isdigit():  # ID MODEL W H params...
        tokens = tokens[1:]
    if len(tokens) < 3:
        raise InputError(f"camera {source}: expected 'MODEL WIDTH HEIGHT params...' (COLMAP cameras.txt line)")
    model = tokens[0].upper()
    if model not in SUPPORTED_MODELS:
        raise InputError(
            f"camera {source}: unsupported camera model {tokens[0]!r} (supported: {', '.join(SUPPORTED_MODELS)})"
        )
    try:
        w, h = int(tokens[1]), int(tokens[2])
        params = [float(t) for t in tokens[3:]]
    except ValueError:
        raise InputError(
            f"camera {source}: width/height must be integers and params numbers: {' '.join(tokens)!r}"
        ) from None
    return Camera(model, w, h, params)


def _camera_from_json(obj, source: str) -> Camera:
    if isinstance(obj, list) and len(obj) == 1:
        obj = obj[0]
    if not isinstance(obj, dict) or not {"model", "width", "height", "params"} <= set(obj):
        raise InputError(f"camera {source}: a JSON camera needs the keys model, width, height, params")
    try:
        return Camera(
            str(obj["model"]).upper(), int(obj["width"]), int(obj["height"]), [float(p) for p in obj["params"]]
        )
    except (TypeError, ValueError):
        raise InputError(f"camera {source}: invalid JSON camera {obj}") from None


def read_camera(spec) -> Camera:
    """A Camera from a COLMAP cameras.txt line, a JSON string, or a file holding either."""
    if isinstance(spec, Camera):
        return spec
    if isinstance(spec, dict):
        return _camera_from_json(spec, "<dict>")
    spec = str(spec)
    text, source = spec.strip(), repr(spec)
    looks_inline = text.startswith("{") or len(text.split()) >= 3
    if not looks_inline:
        path = Path(spec)
        if not path.is_file():
            raise InputError(
                f"camera file not found: {path} (or give a COLMAP camera line 'MODEL W H params...' or a JSON camera)"
            )
        try:
            text = path.read_text().strip()
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"cannot read camera file {path}: {e}") from None
        source = str(path)
    if text.startswith("{") or text.startswith("["):
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"camera {source}: invalid JSON ({e})") from None
        return _camera_from_json(obj, source)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"camera {source}: no camera found")
    return _camera_from_tokens(lines[0].split(), source)


# -- converting poses from other tools into a prior -------------------------------------------------
POSE_SOURCES = (
    "world_from_cam",
    "cam_from_world",
    "opengl",
    "nerf",
    "colmap",
    "tum",
    "7scenes",
)  # see `favormap pose --help`


def _as_path(source: str) -> Path | None:
    """``source`` as a path when it can name one (short, one line), else None (pose text)."""
    return Path(source) if len(source) < 4096 and "\n" not in source else None


def _text_of(source: str) -> tuple[str, str]:
    """(text, label): the file's text when ``source`` names a file, else ``source`` itself."""
    p = _as_path(source)
    if p is not None and p.is_file():
        try:
            return p.read_text(), str(p)
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"cannot read {p}: {e}") from None
    return source, "<argument>"


def _file_in_folder(kind: str, folder: Path, name: str | None) -> Path | np.ndarray:
    """The file of a sequence folder that holds the pose ``name`` in the form ``kind`` (what ``favormap
    build`` reads from such a folder), or, for a COLMAP model, the pose itself (cam_from_world, read
    with pycolmap: binary models too)."""
    if kind not in ("nerf", "colmap", "tum", "7scenes"):
        raise InputError(f"{folder} is a folder: --from {kind} takes a file or the pose text itself")
    if not name:
        what = {"nerf": "a frame's file_path", "colmap": "an image name", "tum": "a timestamp", "7scenes": "a frame"}
        raise InputError(f"{folder} is a folder: --name is needed ({what[kind]})")
    if kind == "nerf":  # as the reader: transforms.json alone where it exists, else the split files
        from .readers import nerf

        if (folder / nerf.FILENAME).is_file():
            return folder / nerf.FILENAME
        files = [f for _, f in nerf.split_files(folder)]
        if not files:
            raise InputError(f"{folder}: no {nerf.FILENAME} (or transforms_train/val/test.json) in this folder")
        for f in files:  # the one that lists the frame; convert_pose reports a damaged one
            try:
                if _nerf_frame(json.loads(_text_of(str(f))[0]).get("frames", ()), name) is not None:
                    return f
            except (json.JSONDecodeError, AttributeError, TypeError):
                return f
        return files[0]
    if kind == "tum":
        f = folder / "groundtruth.txt"
        if not f.is_file():
            raise InputError(f"{folder}: no groundtruth.txt in this folder")
        return f
    if kind == "7scenes":
        stem = name.split(".")[0]  # frame-000000, frame-000000.color.png, frame-000000.pose.txt
        f = folder / f"{stem}.pose.txt"
        if not f.is_file():
            raise InputError(f"{folder}: no {f.name} in this folder")
        return f
    from .readers.colmap import MODEL_DIRS, find_model

    model = find_model(folder)
    if model is None:
        raise InputError(f"{folder}: no COLMAP model (cameras + images .bin/.txt) in {', '.join(MODEL_DIRS)}")
    if (model / "images.txt").is_file():
        return model / "images.txt"
    import pycolmap  # a binary model

    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as e:  # noqa: BLE001 - pycolmap reports parse failures as ValueError/RuntimeError
        raise InputError(f"cannot read the COLMAP model in {model}: {e}") from None
    for im in rec.images.values():
        if name in (im.name, Path(im.name).name, f"images/{im.name}"):
            if not im.has_pose:
                raise InputError(f"{model}: image {im.name!r} is not registered (it has no pose)")
            from ..geometry import from_rigid3d

            return from_rigid3d(im.cam_from_world())
    raise InputError(f"{model}: no image named {name!r}")


def _nerf_frame(frames, name: str):
    """The frame of a transforms.json frame list whose file_path matches ``name`` (the path, its file
    name, or either without the extension); None when there is none."""
    for fr in frames if isinstance(frames, list) else ():
        if not isinstance(fr, dict):
            continue
        fp = str(fr.get("file_path", ""))
        if name in (fp, Path(fp).name, Path(fp).stem, Path(fp).with_suffix("").as_posix()):
            return fr
    return None


def _rigid(R, t, label) -> np.ndarray:
    dev = geometry.rotation_deviation(R)
    if not dev <= _ROT_TOL:
        raise InputError(f"{label}: the rotation is not a rotation (max |R^T R - I| = {dev:.1e} > {_ROT_TOL:.0e})")
    T = np.eye(4)
    T[:3, :3] = geometry.nearest_rotation(R)
    T[:3, 3] = t
    return T


def _quat(q_xyzw, label) -> np.ndarray:
    q = np.asarray(q_xyzw, np.float64)
    if not geometry.quaternion_deviation(q) <= _ROT_TOL:
        raise InputError(f"{label}: not a unit quaternion (norm {np.linalg.norm(q):.6g})")
    return geometry.quat_to_rotmat(q / np.linalg.norm(q))


def _numbers(text: str, label: str) -> np.ndarray:
    tokens = " ".join(ln.split("#", 1)[0].replace(",", " ") for ln in text.splitlines()).split()
    try:
        return np.array([float(t) for t in tokens])
    except ValueError:
        raise InputError(f"{label}: expected numbers only") from None


def convert_pose(kind: str, source: str, name: str | None = None) -> np.ndarray:
    """cam_from_world (4x4, OpenCV axes) of a pose given in another tool's form (``POSE_SOURCES``,
    described in :mod:`favormap.cli.pose`);
    ``source`` is a file, the text itself, or a sequence folder (with ``name``: the file it holds for
    ``kind``, :func:`_file_in_folder`). Write it as a prior with :func:`write_pose`."""
    if kind not in POSE_SOURCES:
        raise InputError(f"unknown pose source {kind!r} (known: {', '.join(POSE_SOURCES)})")
    folder = _as_path(source)
    if folder is not None and folder.is_dir():  # a sequence folder
        found = _file_in_folder(kind, folder, name)
        if isinstance(found, np.ndarray):
            return found
        source = str(found)
    text, label = _text_of(source)
    if kind in ("world_from_cam", "7scenes"):
        vals = _numbers(text, label)
        return geometry.inverse(parse_pose(vals, len([ln for ln in text.splitlines() if ln.strip()]), label))
    if kind in ("cam_from_world", "opengl"):
        return _matrix_pose(text, label, opengl=kind == "opengl")
    if kind == "nerf":
        return _nerf_pose(text, label, name)
    if kind == "colmap":
        return _colmap_pose(text, label, name)
    return _tum_pose(text, label, name)


def _matrix_pose(text: str, label: str, opengl: bool) -> np.ndarray:
    """A 4x4 or 3x4 cam_from_world matrix, or an OpenGL world_from_cam one."""
    vals = _numbers(text, label)
    if len(vals) not in (12, 16):
        raise InputError(f"{label}: expected a 4x4 (16 numbers) or 3x4 (12) matrix, found {len(vals)} numbers")
    M = _matrix(vals, label, "pose")
    T = _rigid(M[:3, :3], M[:3, 3], label)
    if not opengl:
        return T
    return geometry.inverse(geometry.world_from_cam_opengl_to_opencv(T))


def _nerf_pose(text: str, label: str, name: str | None) -> np.ndarray:
    """The transform_matrix of frame ``name`` of a transforms.json."""
    if not name:
        raise InputError("--name is needed with nerf: the file_path (or its file name) of the frame")
    try:
        frames = json.loads(text)["frames"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise InputError(f"{label}: not a transforms.json ({type(e).__name__}: {e})") from None
    fr = _nerf_frame(frames, name)
    if fr is None:
        raise InputError(f"{label}: no frame with file_path {name!r}")
    fp = fr.get("file_path", "")
    try:
        M = np.asarray(fr["transform_matrix"], np.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{label}: {fp}: no 4x4 transform_matrix ({type(e).__name__}: {e})") from None
    M = np.vstack([M, [0, 0, 0, 1]]) if M.shape == (3, 4) else M
    if M.shape != (4, 4):
        raise InputError(f"{label}: {fp}: transform_matrix is {M.shape[0]}x{M.shape[1] if M.ndim > 1 else 1}, not 4x4")
    return geometry.inverse(geometry.world_from_cam_opengl_to_opencv(_rigid(M[:3, :3], M[:3, 3], f"{label}: {fp}")))


def _colmap_pose(text: str, label: str, name: str | None) -> np.ndarray:
    """An images.txt line (of image ``name``) or 'QW QX QY QZ TX TY TZ'."""
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if name:  # images.txt: the first line of each image pair names the image last
        lines = [t for t in lines if len(t) >= 10 and t[9] == name]
        if not lines:
            raise InputError(f"{label}: no image named {name!r}")
    tok = lines[0] if lines else []
    nums = tok[1:8] if len(tok) >= 10 else tok
    vals = _numbers(" ".join(nums), label)
    if len(vals) != 7:
        raise InputError(f"{label}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME' or 'QW QX QY QZ TX TY TZ'")
    qw, qx, qy, qz, tx, ty, tz = vals
    T = np.eye(4)
    T[:3, :3] = _quat([qx, qy, qz, qw], label)
    T[:3, 3] = [tx, ty, tz]
    return T


def _tum_pose(text: str, label: str, name: str | None) -> np.ndarray:
    """One 'timestamp tx ty tz qx qy qz qw' line (world_from_cam), or the one nearest timestamp ``name``."""
    rows = [_numbers(ln, label) for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if name is not None:
        try:
            t0 = float(name)
        except ValueError:
            raise InputError(f"--name for tum is a timestamp, got {name!r}") from None
        rows = [r for r in rows if len(r) == 8]
        if not rows:
            raise InputError(f"{label}: no 'timestamp tx ty tz qx qy qz qw' line")
        rows = [min(rows, key=lambda r: abs(r[0] - t0))]
    if len(rows) != 1 or len(rows[0]) not in (7, 8):
        raise InputError(
            f"{label}: expected one line 'timestamp tx ty tz qx qy qz qw' (or give the file and --name TIMESTAMP)"
        )
    v = rows[0][-7:]
    return geometry.inverse(_rigid(_quat(v[3:], label), v[:3], label))
