"""Writing maps: one HDF5 file, written beside the target and renamed into place (atomic)."""

from __future__ import annotations

import json
import os
import sys
import tempfile
from contextlib import ExitStack, contextmanager
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..errors import FavormapError, MapFormatError
from ..io import Camera
from .fields import field_name, landmark_datasets
from .model import MapData
from .schema import (
    FORMAT,
    FORMAT_VERSION,
    POSE_CONVENTION,
    check_arrays,
    check_attributes,
    check_file,
    check_values,
    load_schema,
    numpy_dtype,
)

PARTIAL_SUFFIX = ".partial"


def check_output_path(path, inputs=()) -> Path:
    """Fail early (before any work) when ``path`` cannot receive an output file: a directory, a
    missing or read-only folder (tried by creating a file there), or the same file as one of
    ``inputs`` (paths; None entries are skipped). Returns ``path`` as a Path."""
    path = Path(path)
    if path.is_dir():
        raise FavormapError(f"output {path} is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise FavormapError(f"output folder does not exist: {parent}")
    for src in inputs:
        if src is not None and path.exists() and Path(src).exists() and os.path.samefile(path, src):
            raise FavormapError(f"output {path} is also an input ({src}); write to another file")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=parent)
    except OSError as e:
        raise FavormapError(f"output folder is not writable: {parent} ({e.strerror or e})") from None
    os.close(fd)
    os.unlink(probe)
    return path


def is_hdf5(path) -> bool:
    """True when ``path`` starts with the HDF5 signature (a map, or what is left of one)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


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


def _stored(data, spec: dict) -> np.ndarray:
    """An array exactly as it is stored: the schema dtype; strings as fixed-length byte strings
    (HDF5 character set ASCII) holding UTF-8 (variable-length strings cannot be checksummed)."""
    if spec["dtype"] == "str":
        if isinstance(data, np.ndarray) and data.dtype.kind == "S":
            return data
        enc = [str(x).encode("utf-8") for x in data]
        width = max([len(e) for e in enc] + [1])
        return np.array(enc, dtype=f"S{width}").reshape(len(enc))
    with np.errstate(over="ignore", invalid="ignore"):
        return np.asarray(data).astype(numpy_dtype(spec["dtype"]), copy=False)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def camera_arrays(cameras: dict[int, Camera]) -> dict[str, np.ndarray]:
    """The cameras/* datasets of a camera dict (ids sorted, params zero padded to 12; the optional
    cameras/working_fov only when a camera has one, 0 standing for the default rule)."""
    K = sorted(cameras)
    params = np.zeros((len(K), 12))
    for i, k in enumerate(K):
        p = cameras[k].params
        params[i, : len(p)] = p
    fov = np.array([cameras[k].working_fov or 0.0 for k in K], np.float64)
    return {
        "cameras/ids": np.array(K, np.int32),
        "cameras/models": [cameras[k].model for k in K],
        "cameras/sizes": np.array([[cameras[k].width, cameras[k].height] for k in K], np.int32).reshape(-1, 2),
        "cameras/params": params,
        **({"cameras/working_fov": fov} if fov.any() else {}),
    }


def check_frames(cameras: dict[int, Camera], names, camera_ids, cam_from_world) -> list[str]:
    """Problems the writer would find in the cameras/* and frames/* datasets of a map made from these
    frames (the schema's value checks). :func:`build.build_map` runs it on its input sequence, so that a
    map the writer would refuse is refused before any image is read, not after the training."""
    datasets = load_schema(FORMAT_VERSION)["datasets"]
    arrays = {
        **camera_arrays(cameras),
        "frames/names": list(names),
        "frames/camera_ids": np.asarray(camera_ids),
        "frames/cam_from_world": np.asarray(cam_from_world),
    }
    try:
        stored = {k: _stored(v, datasets[k]) for k, v in arrays.items()}
    except (TypeError, ValueError) as e:
        return [f"the cameras or poses cannot be stored ({type(e).__name__}: {e})"]
    problems = []
    for k, a in stored.items():
        problems += check_values(k, a, {}, stored)[0]
    return problems


class MapWriter:
    """Write a map file dataset by dataset, large datasets row block by row block.

    Same layout as ``mapfile.write_map`` (schema dtypes, per-landmark chunks for voxel grids,
    Fletcher-32, gzip+shuffle, fixed-length strings holding UTF-8), the same integrity checks (schema
    ``values`` constraints of every array and streamed block, attributes, then the structure of the
    written file) and the same atomicity: the file is written beside ``path`` and renamed into place
    on success, with the ``format`` attribute last::

        with MapWriter(path, header, num_landmarks=L, num_frames=M) as w:
            w.put("landmarks/ids", ids)              # whole datasets
            w.create("voxels/descriptors")            # streamed: shape from L/M/C/R
            w.write_rows("voxels/descriptors", 0, block)
            ...
    Leaving the block without error checks that every schema dataset was written completely; an
    error (or an invalid value) leaves ``path`` untouched. ``header`` holds extractor, channels,
    grid_resolution, patch_size, render_samples, max_side and provenance (a dict)."""

    HEADER_KEYS = ("extractor", "channels", "grid_resolution", "patch_size", "render_samples", "max_side")

    def __init__(self, path, header: dict, num_landmarks: int, num_frames: int, values_checked: bool = False):
        self.path = check_output_path(path)
        # the whole datasets put() gets were checked against the schema's value constraints already
        # (write_map's check_arrays, before any file exists): not again on leaving
        self._values_checked = bool(values_checked)
        missing = [k for k in self.HEADER_KEYS if k not in header]
        if missing:
            raise ValueError(f"MapWriter header lacks {missing}")
        self.header = dict(header)
        self.L, self.M = int(num_landmarks), int(num_frames)
        self.schema = load_schema(FORMAT_VERSION)
        self.dims = {"L": self.L, "M": self.M, "C": int(header["channels"]), "R": int(header["grid_resolution"])}
        self._stack = ExitStack()
        self._tmp: Path | None = None
        self.f: h5py.File | None = None
        self._filled: dict[str, int] = {}  # streamed dataset -> rows written
        self._streamed: set[str] = set()
        self._arrays: dict[str, np.ndarray] = {}  # whole datasets, for the cross-dataset value checks

    # -- context --------------------------------------------------------------------------------
    def __enter__(self) -> MapWriter:
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        self.f = h5py.File(self._tmp, "w", libver="latest")
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                self._finish()
            except BaseException:
                self._close()
                if not self._stack.__exit__(*sys.exc_info()):  # removes the partial file
                    raise
                return False
        self._close()
        return self._stack.__exit__(exc_type, exc, tb)

    def _close(self):
        if self.f is not None:
            try:
                self.f.close()
            finally:
                self.f = None

    # -- datasets -------------------------------------------------------------------------------
    def _spec(self, name: str) -> dict:
        spec = self.schema["datasets"].get(name)
        if spec is None:
            raise KeyError(f"{name!r} is not a dataset of the map schema")
        return spec

    @staticmethod
    def _chunks(spec: dict, shape: tuple) -> tuple:
        n = shape[0]
        if spec.get("chunk") == "landmark":
            return (1,) + tuple(shape[1:])
        row = max(1, int(np.prod(shape[1:])) if len(shape) > 1 else 1)
        return (max(1, min(n, max(1, 65536 // row))),) + tuple(shape[1:])

    def _kw(self, spec: dict, shape: tuple) -> dict:
        if shape[0] == 0:
            kw = dict(maxshape=(None,) + tuple(shape[1:]), chunks=(1,) + tuple(shape[1:]), fletcher32=True)
        else:
            kw = dict(chunks=self._chunks(spec, shape), fletcher32=True)
        kw.update(compression="gzip", compression_opts=4, shuffle=True)
        return kw

    def _refuse(self, problems: list[str]):
        if problems:
            raise MapFormatError(
                f"refusing to write an invalid map to {self.path}: {problems[0]}"
                + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else "")
            )

    def put(self, name: str, data) -> None:
        """Write a whole dataset (cast to the schema dtype)."""
        spec = self._spec(name)
        arr = _stored(data, spec)
        self._check_shape(name, spec, arr.shape)
        self.f.create_dataset(name, data=arr, dtype=arr.dtype, **self._kw(spec, arr.shape))
        self._arrays[name] = arr

    def _shape_of(self, name: str, spec: dict, rows: int | None, given: tuple | None = None) -> tuple:
        """The shape ``name`` must have; symbols the map does not fix yet (O, P) are taken from
        ``rows`` (the first) or the ``given`` shape and fixed for the datasets after it."""
        out, seen = [], {}
        for i, s in enumerate(spec["shape"]):
            if isinstance(s, int):
                out.append(s)
            elif s in self.dims or s in seen:
                out.append(self.dims.get(s, seen.get(s)))
            elif rows is not None and not out:
                out.append(int(rows))
            elif given is not None and i < len(given):
                out.append(seen.setdefault(s, int(given[i])))  # a symbol twice in one shape: equal
            else:
                raise ValueError(f"{name}: give the number of rows along {s!r}")
        if rows is not None and out[0] != rows:
            raise ValueError(f"{name}: {rows} rows given but the map has {out[0]}")
        return tuple(out)

    def _check_shape(self, name: str, spec: dict, shape: tuple) -> None:
        want = self._shape_of(name, spec, shape[0] if len(shape) else None, tuple(shape))
        if tuple(shape) != want:
            raise ValueError(f"{name}: shape {tuple(shape)} does not match the map's {want}")
        for s, n in zip(spec["shape"], shape):
            if isinstance(s, str) and s not in ("L", "M", "C", "R"):
                self.dims.setdefault(s, int(n))

    def create(self, name: str, rows: int | None = None) -> None:
        """Create a dataset to be filled with :meth:`write_rows` (not for string datasets)."""
        spec = self._spec(name)
        if spec["dtype"] == "str":
            raise ValueError("string datasets cannot be streamed")
        shape = self._shape_of(name, spec, rows)
        self.f.create_dataset(name, shape=shape, dtype=numpy_dtype(spec["dtype"]), **self._kw(spec, shape))
        self._streamed.add(name)
        self._filled[name] = 0

    def write_rows(self, name: str, start: int, data) -> None:
        """Write rows ``start .. start+len(data)`` of a created dataset (any trailing shape with the
        right number of elements per row, e.g. (n, R^3, C) for (n, R, R, R, C)). Each block is
        checked against the schema's value constraints of its dataset."""
        ds = self.f[name]
        data = np.asarray(data)
        n = len(data)
        if start < 0 or start + n > ds.shape[0]:
            raise IndexError(f"{name}: rows {start}..{start + n} outside 0..{ds.shape[0]}")
        if n:
            with np.errstate(over="ignore", invalid="ignore"):
                block = data.reshape((n,) + ds.shape[1:]).astype(ds.dtype, copy=False)
            self._refuse([f"{p} (rows {start}..{start + n})" for p in check_values(name, block, self.dims)[0]])
            ds[start : start + n] = block
        self._filled[name] += n

    # -- finish -----------------------------------------------------------------------------------
    def _finish(self) -> None:
        f = self.f
        for name, spec in self.schema["datasets"].items():
            if name not in f and not spec.get("optional"):
                raise FavormapError(f"internal error: map dataset {name!r} was not written")
        for name in self._streamed:
            if self._filled[name] != f[name].shape[0]:
                raise FavormapError(f"internal error: {name!r} got {self._filled[name]} of {f[name].shape[0]} rows")
        problems = []
        for name, arr in ({} if self._values_checked else self._arrays).items():
            problems += check_values(name, arr, self.dims, self._arrays)[0]
        attrs = header_attributes(self.header, self.L, self.M)
        self._refuse(problems + check_attributes(attrs))
        for k, v in attrs.items():
            if k != "format":
                f.attrs[k] = v
        f.flush()
        f.attrs["format"] = FORMAT  # last: a half-written file is not a map
        self._close()
        with h5py.File(self._tmp, "r", locking=False) as g:
            problems = check_file(g)
        if problems:  # a writer bug; never rename a bad file into place
            raise MapFormatError(f"written map failed its schema check: {problems[0]}")


def header_attributes(header: dict, num_landmarks: int, num_frames: int) -> dict:
    """The root attributes of a map file."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "favormap_version": __version__,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "extractor": str(header["extractor"]),
        **{k: int(header[k]) for k in ("channels", "grid_resolution", "patch_size", "render_samples", "max_side")},
        "pose_convention": POSE_CONVENTION,
        "num_landmarks": int(num_landmarks),
        "num_frames": int(num_frames),
        "provenance": json.dumps(header.get("provenance", {}), default=_json_default),
    }


def map_header(m: MapData) -> dict:
    return {**{k: getattr(m, k) for k in MapWriter.HEADER_KEYS}, "provenance": m.provenance}


def map_arrays(m: MapData) -> dict:
    """Every schema dataset of an in-memory map, keyed by its path in the file."""
    return {
        **{p: getattr(m, field_name(p)) for p in landmark_datasets()},
        **camera_arrays(m.cameras),
        "frames/names": list(m.frame_names),
        "frames/camera_ids": m.frame_camera_ids,
        "frames/cam_from_world": m.cam_from_world,
        "tracks/landmark_index": m.track_landmark,
        "tracks/frame_index": m.track_frame,
        "tracks/xy": m.track_xy,
        **({} if m.track_patch is None else {"tracks/patch": m.track_patch}),
        **({} if m.cam_from_rig is None else {"frames/cam_from_rig": np.asarray(m.cam_from_rig, np.float64)}),
    }


def _write_contents(w: MapWriter, arrays: dict) -> None:
    for name, data in arrays.items():
        w.put(name, data)


def write_map(m: MapData, path) -> Path:
    """Write ``m`` to ``path`` atomically (see :func:`atomic_path`).

    Integrity: the map is checked against the schema (structure and values) before any file is
    created, so favormap never writes a map it would refuse to read; every dataset is written with
    a Fletcher-32 checksum; the magic attribute ``format`` is written last and the written file is
    checked again before it is renamed into place."""
    path = Path(path)
    try:
        header = map_header(m)
        arrays = map_arrays(m)
        stored = {
            k: _stored(arrays[k], spec)
            for k, spec in load_schema(FORMAT_VERSION)["datasets"].items()
            if k in arrays or not spec.get("optional")
        }
        problems = check_arrays(stored, header_attributes(header, m.num_landmarks, m.num_frames))
    except (TypeError, ValueError, AttributeError, KeyError) as e:
        raise MapFormatError(
            f"refusing to write {path}: the map cannot be serialised ({type(e).__name__}: {e})"
        ) from None
    if problems:
        raise MapFormatError(
            f"refusing to write an invalid map to {path}: {problems[0]}"
            + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else "")
        )
    with MapWriter(path, header, m.num_landmarks, m.num_frames, values_checked=True) as w:
        _write_contents(w, stored)
    return path
