"""Writing maps: one HDF5 file, written beside the target and renamed into place (atomic)."""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..errors import FavormapError, MapFormatError
from .model import MapData
from .schema import (
    FORMAT,
    FORMAT_VERSION,
    check_arrays,
    check_file,
    load_schema,
    numpy_dtype,
)

POSE_CONVENTION = ("cam_from_world 4x4; OpenCV camera axes (x right, y down, z forward); "
                   "pixel centre of the top-left pixel at (0.5, 0.5)")


PARTIAL_SUFFIX = ".partial"


def check_output_path(path) -> Path:
    """Fail early (before any work) when ``path`` cannot receive an output file: a directory, a
    missing or read-only folder. Returns ``path`` as a Path."""
    path = Path(path)
    if path.is_dir():
        raise FavormapError(f"output {path} is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FavormapError(f"output folder does not exist: {parent}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise FavormapError(f"output folder is not writable: {parent}")
    return path


def _fsync_dir(folder: Path):
    try:
        dfd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path`` (``.NAME.XXXXXXXX.partial``, hidden, never a name a
    user would open); on success fsync it and rename it over ``path`` (an atomic replace), then
    fsync the folder. On an error the temporary file is removed and ``path`` is untouched; after
    a kill or power loss ``path`` is either the old file, absent, or the complete new file (a
    stray hidden ``.partial`` file may remain and can be deleted)."""
    path = check_output_path(path)
    parent = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=PARTIAL_SUFFIX, dir=parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        # mkstemp creates 0600 files: give the result the mode a plain open() would (or keep the
        # mode of the file it replaces)
        try:
            mode = path.stat().st_mode & 0o7777
        except OSError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        _fsync_dir(parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _dataset_arrays(m: MapData) -> dict[str, np.ndarray]:
    K = sorted(m.cameras)
    params = np.zeros((len(K), 12))
    for i, k in enumerate(K):
        p = m.cameras[k].params
        params[i, : len(p)] = p
    return {
        "landmarks/ids": m.ids,
        "landmarks/positions": m.positions,
        "landmarks/voxel_size": m.voxel_size,
        "landmarks/track_length": m.track_length,
        "landmarks/reproj_error": m.reproj_error,
        "landmarks/quality": m.quality,
        "landmarks/cosine": m.cosine,
        "landmarks/view_dir": m.view_dir,
        "landmarks/view_angle": m.view_angle,
        "landmarks/depth_range": m.depth_range,
        "landmarks/mean_descriptor": m.mean_descriptor,
        "voxels/descriptors": m.descriptors,
        "voxels/density": m.density,
        "cameras/ids": np.array(K, np.int32),
        "cameras/models": np.array([m.cameras[k].model for k in K], dtype=object),
        "cameras/sizes": np.array([[m.cameras[k].width, m.cameras[k].height] for k in K], np.int32).reshape(-1, 2),
        "cameras/params": params,
        "frames/names": np.array(m.frame_names, dtype=object),
        "frames/camera_ids": m.frame_camera_ids,
        "frames/cam_from_world": m.cam_from_world,
        "tracks/landmark_index": m.track_landmark,
        "tracks/frame_index": m.track_frame,
        "tracks/xy": m.track_xy,
    }


def _stored_arrays(m: MapData) -> dict[str, np.ndarray]:
    """The arrays exactly as they are stored: schema dtypes, strings as fixed-length UTF-8
    (variable-length strings cannot be checksummed)."""
    arrays = _dataset_arrays(m)
    out = {}
    for path, spec in load_schema(FORMAT_VERSION)["datasets"].items():
        data = arrays[path]
        if spec["dtype"] == "str":
            enc = [str(x).encode("utf-8") for x in data]
            width = max([len(e) for e in enc] + [1])
            out[path] = np.array(enc, dtype=f"S{width}")
        else:
            with np.errstate(over="ignore", invalid="ignore"):
                out[path] = np.asarray(data).astype(numpy_dtype(spec["dtype"]), copy=False)
    return out


def _write_contents(f: h5py.File, arrays: dict[str, np.ndarray], attrs: dict):
    for path, spec in load_schema(FORMAT_VERSION)["datasets"].items():
        data = arrays[path]
        n = len(data)
        if spec.get("chunk") == "landmark":
            chunks = (1,) + tuple(data.shape[1:])
        else:
            row = max(1, int(np.prod(data.shape[1:])) if data.ndim > 1 else 1)
            chunks = (max(1, min(n, max(1, 65536 // row))),) + tuple(data.shape[1:])
        kw = dict(chunks=chunks, fletcher32=True)
        if n == 0:
            kw = dict(maxshape=(None,) + tuple(data.shape[1:]), chunks=(1,) + tuple(data.shape[1:]), fletcher32=True)
        kw.update(compression="gzip", compression_opts=4, shuffle=True)
        f.create_dataset(path, data=data, dtype=data.dtype, **kw)
    for k, v in attrs.items():
        if k != "format":  # the magic goes last (write_map)
            f.attrs[k] = v


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _attributes(m: MapData) -> dict:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "favormap_version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "extractor": m.extractor,
        "channels": int(m.channels),
        "grid_resolution": int(m.grid_resolution),
        "patch_size": int(m.patch_size),
        "render_samples": int(m.render_samples),
        "max_side": int(m.max_side),
        "pose_convention": POSE_CONVENTION,
        "num_landmarks": int(m.num_landmarks),
        "num_frames": int(m.num_frames),
        "provenance": json.dumps(m.provenance, default=_json_default),
    }


def write_map(m: MapData, path) -> Path:
    """Write ``m`` to ``path`` atomically (see :func:`atomic_path`).

    Integrity: the map is checked against the schema (structure and values) before any file is
    created, so favormap never writes a map it would refuse to read; every dataset is written with
    a Fletcher-32 checksum; the magic attribute ``format`` is written last and the written file is
    checked again before it is renamed into place."""
    path = Path(path)
    try:
        attrs = _attributes(m)
        arrays = _stored_arrays(m)
        problems = check_arrays(arrays, attrs)
    except (TypeError, ValueError, AttributeError) as e:
        raise MapFormatError(f"refusing to write {path}: the map cannot be serialised ({type(e).__name__}: {e})") from None
    if problems:
        raise MapFormatError(f"refusing to write an invalid map to {path}: {problems[0]}"
                             + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""))
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", libver="latest") as f:
            _write_contents(f, arrays, attrs)
            f.flush()
            f.attrs["format"] = FORMAT
        with h5py.File(tmp, "r", locking=False) as f:
            problems = check_file(f)
        if problems:  # pragma: no cover - a writer bug; never rename a bad file into place
            raise MapFormatError(f"written map failed its schema check: {problems[0]}")
    return path
