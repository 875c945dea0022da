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
from ..errors import FavormapError
from .model import MapData
from .schema import FORMAT, FORMAT_VERSION, load_schema, numpy_dtype

POSE_CONVENTION = ("cam_from_world 4x4; OpenCV camera axes (x right, y down, z forward); "
                   "pixel centre of the top-left pixel at (0.5, 0.5)")


@contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; on success fsync it and rename it over ``path``.
    On any error (or a kill) ``path`` is untouched and the temporary file is removed/hidden."""
    path = Path(path)
    if path.exists() and path.is_dir():
        raise FavormapError(f"output {path} is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FavormapError(f"output folder does not exist: {parent}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        try:
            dfd = os.open(parent, os.O_RDONLY)
            os.fsync(dfd)
            os.close(dfd)
        except OSError:
            pass
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


def _write_contents(f: h5py.File, m: MapData):
    schema = load_schema(FORMAT_VERSION)
    arrays = _dataset_arrays(m)
    for path, spec in schema["datasets"].items():
        data = arrays[path]
        dtype = numpy_dtype(spec["dtype"])
        n = len(data)
        if spec.get("chunk") == "landmark":
            chunks = (1,) + tuple(data.shape[1:])
        else:
            row = max(1, int(np.prod(data.shape[1:])) if data.ndim > 1 else 1)
            chunks = (max(1, min(n, max(1, 65536 // row))),) + tuple(data.shape[1:])
        kw = dict(chunks=chunks if n else None, fletcher32=True)
        if n == 0:
            kw = dict(maxshape=(None,) + tuple(data.shape[1:]), chunks=(1,) + tuple(data.shape[1:]), fletcher32=True)
        if spec["dtype"] == "str":  # fixed-length UTF-8 (variable-length strings cannot be checksummed)
            enc = [str(x).encode("utf-8") for x in data]
            width = max([len(e) for e in enc] + [1])
            data = np.array(enc, dtype=f"S{width}")
            dtype = data.dtype
        else:
            data = np.asarray(data).astype(dtype, copy=False)
        kw.update(compression="gzip", compression_opts=4, shuffle=True)
        f.create_dataset(path, data=data, dtype=dtype, **kw)
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["favormap_version"] = __version__
    f.attrs["created"] = now
    f.attrs["extractor"] = m.extractor
    f.attrs["channels"] = int(m.channels)
    f.attrs["grid_resolution"] = int(m.grid_resolution)
    f.attrs["patch_size"] = int(m.patch_size)
    f.attrs["render_samples"] = int(m.render_samples)
    f.attrs["max_side"] = int(m.max_side)
    f.attrs["pose_convention"] = POSE_CONVENTION
    f.attrs["num_landmarks"] = int(m.num_landmarks)
    f.attrs["num_frames"] = int(m.num_frames)
    f.attrs["provenance"] = json.dumps(m.provenance, default=_json_default)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_map(m: MapData, path) -> Path:
    """Write ``m`` to ``path`` atomically. The magic attribute ``format`` is written last."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w", libver="latest") as f:
            _write_contents(f, m)
            f.flush()
            f.attrs["format"] = FORMAT
    return path
