"""Reading maps lazily: metadata and landmark arrays at open, voxel grids on demand."""

from __future__ import annotations

import json
import threading
from contextlib import contextmanager
from pathlib import Path

import h5py
import numpy as np

from ..errors import FavormapError, InputError, MapFormatError, first_line
from ..geometry import inverse, rotation_angle_deg
from ..io import Camera
from .fields import bulk_datasets, field_name, metadata_datasets
from .model import (
    MapCounts,
    MapData,
    built_for_exact_poses,
    map_aligns_by_default,
    map_estimated_poses,
    median_landmark_reproj_error,
)
from .schema import FORMAT, MapView, check_structure, check_values, open_view


def _open_h5(path: Path) -> h5py.File:
    """Open read-only without HDF5 file locking: a map at its final path is complete and never
    modified (writers write beside it and rename), so readers need no lock, and locking fails on
    file systems without it (NFS, some containers)."""
    path = Path(path)
    if not path.exists():
        raise MapFormatError(f"map not found: {path}")
    if path.is_dir():
        raise MapFormatError(f"{path} is a directory, not a map file")
    try:
        return h5py.File(path, "r", locking=False)
    except Exception as e:  # noqa: BLE001 - OSError mostly; anything from a hostile file
        if isinstance(e, OSError) and "truncated" in str(e):
            raise MapFormatError(f"{path} is not a complete favormap map (truncated HDF5 file)") from None
        raise MapFormatError(f"{path} is not a favormap map (not a readable HDF5 file: {first_line(e)})") from None


@contextmanager
def _guard(path: Path, what: str):
    """Any failure of h5py on a damaged file becomes one MapFormatError (OSError: checksum or I/O)."""
    try:
        yield
    except FavormapError:
        raise
    except OSError as e:
        raise MapFormatError(f"{path}: {what} is corrupted (checksum or read error: {first_line(e)})") from None
    except Exception as e:  # noqa: BLE001 - h5py/numpy raise KeyError, ValueError, RuntimeError, ... on damage
        raise MapFormatError(f"{path}: {what} is corrupted ({type(e).__name__}: {first_line(e)})") from None


def _read_rows(ds, rows: np.ndarray) -> np.ndarray:
    """Rows ``rows`` (any order, repeats allowed) of an h5py dataset, which reads increasing unique indices."""
    out = np.empty((len(rows),) + ds.shape[1:], ds.dtype)
    if len(rows):
        uniq, inv = np.unique(rows, return_inverse=True)
        out[:] = ds[uniq][inv.ravel()]
    return out


def _strings(a) -> list[str]:
    return [s.decode("utf-8", "replace") if isinstance(s, bytes) else str(s) for s in np.asarray(a).ravel().tolist()]


# the voxel cache of a map opened without a size: the whole map where its grids fit this many bytes
DEFAULT_CACHE_BYTES = 1 << 30


def _check_cache_args(cache_size, cache_bytes) -> None:
    """The voxel cache's size: in grids or in bytes, not both, an integer >= 1."""
    if cache_size is not None and cache_bytes is not None:
        raise InputError("give the voxel cache's size in grids (cache_size) or in bytes (cache_bytes), not both")
    for name, v in (("cache_size", cache_size), ("cache_bytes", cache_bytes)):
        if v is not None and not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1):
            raise InputError(f"{name} must be an integer >= 1, not {v!r}")


class Map(MapCounts):
    """A favormap map opened lazily. Landmark metadata is in memory; voxel grids are read for the
    landmarks asked for, in sorted chunk reads, through a cache of ``cache_bytes`` (by default
    DEFAULT_CACHE_BYTES: the whole map where it fits, so that a warm localizer reads nothing) or of
    ``cache_size`` grids.

    Opening checks the header (refusing newer format versions), the structure against the schema
    and the values of the arrays read at open; maps of older versions are migrated in memory.
    Every problem of a damaged file surfaces as :class:`~favormap.errors.MapFormatError`."""

    def __init__(self, path, cache_size: int | None = None, cache_bytes: int | None = None):
        self._f = None
        _check_cache_args(cache_size, cache_bytes)
        self.path = Path(path)
        self._f = _open_h5(self.path)
        self.bytes_read = 0  # voxel bytes read from disk (tests and benchmarks look at it)
        self._slot = None  # row -> cache slot (created on the first voxel read)
        self._lock = threading.Lock()  # voxels() may be called from several threads (a shared Localizer)
        try:
            self._view = self._checked_view()
            self._read_header(self._view.attrs)
            arrays = self._read_metadata()
            self.cameras = self._read_cameras(arrays)
        except BaseException as e:
            self.close()
            if isinstance(e, FavormapError) or not isinstance(e, Exception):
                raise
            raise MapFormatError(f"{self.path} is corrupted: {type(e).__name__}: {first_line(e)}") from None
        self._index = None
        # the voxel cache: the grids of cache_bytes (DEFAULT_CACHE_BYTES), at most the whole map, unless a
        # number of grids is given
        if cache_size is None:
            cache_size = min(max(len(self), 1), max(int(cache_bytes or DEFAULT_CACHE_BYTES) // self.grid_bytes, 1))
        self.cache_size = int(cache_size)

    def _checked_view(self) -> MapView:
        """The file's view, its structure checked against the schema."""
        with _guard(self.path, "the file structure (HDF5 metadata)"):
            view = open_view(self._f, self.path)
        problems = check_structure(view)
        if problems:
            raise MapFormatError(
                f"{self.path} is not a valid favormap map: {problems[0]}"
                + (f" (+{len(problems) - 1} more problems; run favormap validate)" if len(problems) > 1 else "")
            )
        return view

    def _read_header(self, a) -> None:
        """The map's attributes: extractor, sizes, versions and provenance."""
        self.extractor = str(a["extractor"])
        self.channels = int(a["channels"])
        self.grid_resolution = int(a["grid_resolution"])
        self.patch_size = int(a["patch_size"])
        self.render_samples = int(a["render_samples"])
        self.max_side = int(a["max_side"])
        self.format_version = int(a["format_version"])
        self.created = str(a["created"])
        self.favormap_version = str(a["favormap_version"])
        self.provenance = json.loads(a["provenance"])

    def _read_metadata(self) -> dict[str, np.ndarray]:
        """The landmarks' metadata and the frames, read whole and checked (the voxel grids stay on disk);
        returns the arrays read, the cameras' among them."""
        arrays = {}
        for p in (
            *metadata_datasets(),
            "frames/names",
            "frames/camera_ids",
            "frames/cam_from_world",
            "cameras/ids",
            "cameras/models",
            "cameras/sizes",
            "cameras/params",
        ):
            with _guard(self.path, repr(p)):
                arrays[p] = self._ds(p)[()]
        self._check_values(arrays)
        for p in metadata_datasets():  # ids, positions, quality, view cone, ...
            setattr(self, field_name(p), arrays[p])
        self.frame_names = _strings(arrays["frames/names"])
        self.frame_camera_ids = arrays["frames/camera_ids"]
        self.cam_from_world = arrays["frames/cam_from_world"]
        self.stored_cam_from_rig = None  # frames/cam_from_rig where the map has it
        if self._ds("frames/cam_from_rig") is not None:
            with _guard(self.path, "'frames/cam_from_rig'"):
                self.stored_cam_from_rig = self._ds("frames/cam_from_rig")[()]
                self._check_values({"frames/cam_from_rig": self.stored_cam_from_rig})
        return arrays

    @property
    def cam_from_rig(self) -> np.ndarray:
        """(4, 4) the camera's pose in the frame of the poses the map was built from (frames/cam_from_rig; the
        identity where the map has none): ``cam_from_world`` holds the cameras' poses, ``cam_from_rig @
        rig_from_world``, and the localizer takes priors and reports poses as ``rig_from_world``."""
        return np.eye(4) if self.stored_cam_from_rig is None else np.asarray(self.stored_cam_from_rig, np.float64)

    @property
    def rig_from_world(self) -> np.ndarray:
        """(M, 4, 4) the mapping frames' poses in the convention of the poses the map was built from."""
        return np.einsum("ij,njk->nik", inverse(self.cam_from_rig), self.cam_from_world)

    def _read_cameras(self, arrays: dict[str, np.ndarray]) -> dict[int, Camera]:
        """The cameras by id, with their working field of view where the map stores one."""
        from ..io.types import SUPPORTED_MODELS

        cameras = {}
        fov = np.zeros(len(arrays["cameras/ids"]))
        if self._ds("cameras/working_fov") is not None:  # optional: 0 = the default rule
            with _guard(self.path, "'cameras/working_fov'"):
                fov = self._ds("cameras/working_fov")[()]
                self._check_values({"cameras/working_fov": fov})
        for cid, model, (w, h), params, wf in zip(
            arrays["cameras/ids"],
            _strings(arrays["cameras/models"]),
            arrays["cameras/sizes"],
            arrays["cameras/params"],
            fov,
        ):
            try:
                cameras[int(cid)] = Camera(
                    model, int(w), int(h), params[: len(SUPPORTED_MODELS[model])], float(wf) or None
                )
            except FavormapError as e:
                raise MapFormatError(f"{self.path}: invalid camera {int(cid)}: {e}") from None
        return cameras

    @property
    def grid_bytes(self) -> int:
        """Bytes one landmark's grids take in the voxel cache (float32 descriptors and density)."""
        return self.grid_resolution**3 * (self.channels + 1) * 4

    @property
    def cache_bytes(self) -> int:
        """What a warm voxel cache holds (bytes)."""
        return self.cache_size * self.grid_bytes

    def _ds(self, path: str):
        return self._view.datasets[path]

    def _check_values(self, arrays: dict):
        dims = self._view.dims()
        for p, a in arrays.items():
            problems = check_values(p, a, dims, arrays)[0]
            if problems:
                raise MapFormatError(f"{self.path} is not a valid favormap map: {problems[0]} (run favormap validate)")

    # -- basics ----------------------------------------------------------------------------------
    @classmethod
    def open(cls, path, **kw) -> Map:
        return cls(path, **kw)

    def close(self):
        f, self._f = self._f, None
        if f is not None:
            try:
                f.close()
            except Exception:  # noqa: BLE001 - closing a damaged file must not mask the real error
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def file_size(self) -> int:
        return self.path.stat().st_size

    def info(self) -> dict:
        st = self.provenance.get("stats", {})
        return {
            "path": str(self.path),
            "format": FORMAT,
            "format_version": self.format_version,
            "favormap_version": self.favormap_version,
            "created": self.created,
            "num_landmarks": self.num_landmarks,
            "num_frames": self.num_frames,
            "num_cameras": len(self.cameras),
            "extractor": self.extractor,
            "channels": self.channels,
            "grid_resolution": self.grid_resolution,
            "patch_size": self.patch_size,
            "render_samples": self.render_samples,
            "max_side": self.max_side,
            "file_size": self.file_size,
            # memory of a warm localizer's voxel cache holding every grid (float32), against DEFAULT_CACHE_BYTES
            "voxel_memory_bytes": len(self) * self.grid_bytes,
            "align_patches": self.track_patch_radius,  # R of the stored observation patches (0: none)
            # built for exact poses (BuildConfig.exact_poses): localize aligns the inliers' keypoints by default
            "exact_poses": built_for_exact_poses(self.provenance),
            "aligns_by_default": map_aligns_by_default(self.provenance),  # localize aligns unless told otherwise
            "mean_track_length": float(np.mean(self.track_length)) if len(self) else 0.0,
            "median_reproj_error_px": median_landmark_reproj_error(self.reproj_error, self.track_length),
            "median_psnr": float(np.median(self.quality)) if len(self) else None,
            "bbox": [self.positions.min(0).tolist(), self.positions.max(0).tolist()] if len(self) else None,
            "build_stats": st,
            # poses estimated from the images (build of unposed images): how, and the units (None: poses given)
            "estimated_poses": map_estimated_poses(self.provenance),
            # the angle by which the images' camera is turned against the poses the map was built from
            "camera_rotation_deg": float(rotation_angle_deg(self.cam_from_rig[:3, :3])),
        }

    # -- lazy voxel access -------------------------------------------------------------------------
    def voxels(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """Descriptor grids (n, R^3, C) float32 and raw densities (n, R^3) of landmark rows.

        Rows not in the cache are read in sorted contiguous runs; the cache is a fixed-size ring of
        ``cache_size`` grids (oldest inserted evicted first), indexed by a row -> slot array, so a
        call costs a few numpy operations whatever the number of rows. Thread-safe."""
        rows = np.asarray(rows, np.int64).ravel()
        if len(rows) and (rows.min() < 0 or rows.max() >= len(self)):
            raise IndexError("landmark row out of range")
        with self._lock:
            return self._voxels(rows)

    def _voxels(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R3 = self.grid_resolution**3
        if self._slot is None:
            self._slot = np.full(len(self), -1, np.int64)
            self._slot_row = np.full(self.cache_size, -1, np.int64)
            self._cache_d = np.empty((self.cache_size, R3, self.channels), np.float32)
            self._cache_s = np.empty((self.cache_size, R3), np.float32)
            self._next = 0
        slots = self._slot[rows]
        hit = slots >= 0
        if hit.all():  # warm (a localizer's next query): one gather, ~5x faster than the masked copies
            return np.take(self._cache_d, slots, axis=0), np.take(self._cache_s, slots, axis=0)
        desc = np.empty((len(rows), R3, self.channels), np.float32)
        dens = np.empty((len(rows), R3), np.float32)
        desc[hit], dens[hit] = self._cache_d[slots[hit]], self._cache_s[slots[hit]]
        missing, inverse = np.unique(rows[~hit], return_inverse=True)
        if len(missing):
            d, s = self._read_rows(missing)
            desc[~hit], dens[~hit] = d[inverse], s[inverse]
            keep = missing[-self.cache_size :], d[-self.cache_size :], s[-self.cache_size :]
            new = (self._next + np.arange(len(keep[0]))) % self.cache_size
            old = self._slot_row[new]
            self._slot[old[old >= 0]] = -1
            self._slot_row[new] = keep[0]
            self._slot[keep[0]] = new
            self._cache_d[new], self._cache_s[new] = keep[1], keep[2]
            self._next = int((self._next + len(new)) % self.cache_size)
        return desc, dens

    def _read_rows(self, rows: np.ndarray):
        """Read sorted landmark rows: contiguous runs are read with one slice each."""
        if self._f is None:
            raise MapFormatError(f"{self.path}: map is closed")
        dd = self._ds("voxels/descriptors")
        ds = self._ds("voxels/density")
        R3 = self.grid_resolution**3
        out_d = np.empty((len(rows), R3, self.channels), np.float32)
        out_s = np.empty((len(rows), R3), np.float32)
        breaks = np.flatnonzero(np.diff(rows) != 1) + 1
        with _guard(self.path, "voxel data"):
            for run in np.split(np.arange(len(rows)), breaks):
                a, b = int(rows[run[0]]), int(rows[run[-1]]) + 1
                out_d[run] = dd[a:b].reshape(b - a, R3, self.channels)
                out_s[run] = ds[a:b].reshape(b - a, R3)
                self.bytes_read += (b - a) * R3 * (self.channels * dd.dtype.itemsize + ds.dtype.itemsize)
        return out_d, out_s

    def mean_descriptors(self, rows) -> np.ndarray:
        return self.landmark_rows("landmarks/mean_descriptor", rows).astype(np.float32, copy=False)

    def landmark_rows(self, path: str, rows) -> np.ndarray:
        """Rows of one bulk per-landmark dataset (``landmarks/mean_descriptor``, or any the schema adds;
        voxel grids: :meth:`voxels`), in the dataset's dtype."""
        rows = np.asarray(rows, np.int64).ravel()
        if len(rows) and (rows.min() < 0 or rows.max() >= len(self)):
            raise IndexError("landmark row out of range")
        with _guard(self.path, repr(path)):
            return _read_rows(self._ds(path), rows)

    def tracks(self):
        """(landmark_index, frame_index, xy) of all observations, checked against the schema."""
        arrays = {}
        for p in ("tracks/landmark_index", "tracks/frame_index", "tracks/xy"):
            with _guard(self.path, repr(p)):
                arrays[p] = self._ds(p)[()]
        self._check_values(arrays)
        return arrays["tracks/landmark_index"], arrays["tracks/frame_index"], arrays["tracks/xy"]

    @property
    def has_track_patches(self) -> bool:
        """Whether the map stores each observation's grey pixels (optional dataset ``tracks/patch``)."""
        return self._ds("tracks/patch") is not None

    @property
    def track_patch_radius(self) -> int:
        """R of the stored (2R+1) x (2R+1) observation patches (0: none stored)."""
        return (int(self._ds("tracks/patch").shape[1]) - 1) // 2 if self.has_track_patches else 0

    def track_patches(self, obs=None) -> np.ndarray:
        """The stored grey patches (n, P, P) uint8 of observation rows ``obs`` (None: all; a slice: that
        range, read as one block, far faster than the same rows as an index array)."""
        if not self.has_track_patches:
            raise MapFormatError(f"{self.path} stores no observation patches (build it with --align-patches)")
        ds = self._ds("tracks/patch")
        with _guard(self.path, "'tracks/patch'"):
            if obs is None or isinstance(obs, slice):
                return ds[()] if obs is None else ds[obs]
            obs = np.asarray(obs, np.int64).ravel()
            if len(obs) and (obs.min() < 0 or obs.max() >= ds.shape[0]):
                raise IndexError("observation row out of range")
            return _read_rows(ds, obs)

    def load(self) -> MapData:
        """Everything in memory (for merge/prune/export of small maps)."""
        arrays = {}
        for p in bulk_datasets():
            with _guard(self.path, "voxel data" if p.startswith("voxels/") else repr(p)):
                a = self._ds(p)[()]
            arrays[field_name(p)] = a.astype(np.float32) if a.dtype.kind == "f" else a
        arrays.update({field_name(p): getattr(self, field_name(p)) for p in metadata_datasets()})
        kw, extra = MapData.split_landmark_arrays(arrays)
        tl, tf, txy = self.tracks()
        return MapData(
            extractor=self.extractor,
            channels=self.channels,
            grid_resolution=self.grid_resolution,
            patch_size=self.patch_size,
            render_samples=self.render_samples,
            max_side=self.max_side,
            cameras=dict(self.cameras),
            frame_names=list(self.frame_names),
            frame_camera_ids=self.frame_camera_ids,
            cam_from_world=self.cam_from_world,
            track_landmark=tl,
            track_frame=tf,
            track_xy=txy,
            provenance=dict(self.provenance),
            extra=extra,
            track_patch=self.track_patches() if self.has_track_patches else None,
            cam_from_rig=self.stored_cam_from_rig,
            **kw,
        )
