"""Reading maps lazily: metadata and landmark arrays at open, voxel grids on demand."""

from __future__ import annotations

import json
from collections import OrderedDict
from pathlib import Path

import h5py
import numpy as np

from ..errors import MapFormatError
from ..io import Camera
from .model import MapData
from .schema import FORMAT, FORMAT_VERSION, check_file

_LANDMARK_ARRAYS = ("positions", "voxel_size", "track_length", "reproj_error", "quality", "cosine",
                    "view_dir", "view_angle", "depth_range")


def _open_h5(path: Path) -> h5py.File:
    path = Path(path)
    if not path.exists():
        raise MapFormatError(f"map not found: {path}")
    if path.is_dir():
        raise MapFormatError(f"{path} is a directory, not a map file")
    try:
        return h5py.File(path, "r", locking=False)
    except OSError as e:
        raise MapFormatError(f"{path} is not a favormap map (not a readable HDF5 file: {str(e).splitlines()[0]})") from None


def _check_header(f: h5py.File, path: Path):
    fmt = f.attrs.get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode()
    if fmt != FORMAT:
        raise MapFormatError(f"{path} is not a favormap map (HDF5 file without format={FORMAT!r}; maybe incomplete)")
    ver = f.attrs.get("format_version")
    if not isinstance(ver, (int, np.integer)):
        raise MapFormatError(f"{path}: missing or invalid format_version")
    if ver > FORMAT_VERSION:
        raise MapFormatError(f"{path} has map format version {ver}, this favormap reads up to {FORMAT_VERSION}: upgrade favormap")
    if ver < 1:
        raise MapFormatError(f"{path}: invalid format_version {ver}")


class Map:
    """A favormap map opened lazily. Landmark metadata is in memory; voxel grids are read for the
    landmarks asked for, in sorted chunk reads, through a small LRU cache."""

    def __init__(self, path, cache_size: int = 4096):
        self.path = Path(path)
        self._f = _open_h5(self.path)
        self.bytes_read = 0  # voxel bytes read from disk (tests and benchmarks look at it)
        self._cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.cache_size = cache_size
        try:
            _check_header(self._f, self.path)
            problems = check_file(self._f)
            if problems:
                raise MapFormatError(f"{self.path} is not a valid favormap map: {problems[0]}" + (f" (+{len(problems) - 1} more problems; run favormap validate)" if len(problems) > 1 else ""))
            a = self._f.attrs
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
            g = self._f["landmarks"]
            self.ids = g["ids"][()]
            for k in _LANDMARK_ARRAYS:
                setattr(self, k, g[k][()])
            fr = self._f["frames"]
            self.frame_names = [s.decode() if isinstance(s, bytes) else str(s) for s in fr["names"][()]]
            self.frame_camera_ids = fr["camera_ids"][()]
            self.cam_from_world = fr["cam_from_world"][()]
            c = self._f["cameras"]
            models = [s.decode() if isinstance(s, bytes) else str(s) for s in c["models"][()]]
            self.cameras = {}
            for cid, model, (w, h), params in zip(c["ids"][()], models, c["sizes"][()], c["params"][()]):
                from ..io.types import SUPPORTED_MODELS

                n = len(SUPPORTED_MODELS.get(model, ()))
                self.cameras[int(cid)] = Camera(model, int(w), int(h), params[:n])
        except MapFormatError:
            self._f.close()
            raise
        except (OSError, KeyError, ValueError, TypeError, json.JSONDecodeError) as e:
            self._f.close()
            raise MapFormatError(f"{self.path} is corrupted: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
        self._index = None

    # -- basics ----------------------------------------------------------------------------------
    @classmethod
    def open(cls, path, **kw) -> "Map":
        return cls(path, **kw)

    def close(self):
        if self._f:
            self._f.close()
            self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def num_landmarks(self) -> int:
        return len(self.ids)

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)

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
            "mean_track_length": float(np.mean(self.track_length)) if len(self) else 0.0,
            "median_reproj_error_px": float(np.median(self.reproj_error)) if len(self) else None,
            "median_psnr": float(np.median(self.quality)) if len(self) else None,
            "bbox": [self.positions.min(0).tolist(), self.positions.max(0).tolist()] if len(self) else None,
            "build_stats": st,
        }

    # -- lazy voxel access -------------------------------------------------------------------------
    def voxels(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """Descriptor grids (n, R^3, C) float32 and raw densities (n, R^3) of landmark rows."""
        rows = np.asarray(rows, np.int64).ravel()
        if len(rows) and (rows.min() < 0 or rows.max() >= len(self)):
            raise IndexError("landmark row out of range")
        cache = self._cache
        missing = np.unique([r for r in rows.tolist() if r not in cache]).astype(np.int64)
        fresh = {}
        if len(missing):
            d, s = self._read_rows(missing)
            fresh = {int(r): (d[i], s[i]) for i, r in enumerate(missing)}
        out = [fresh.get(r) or cache[r] for r in rows.tolist()]
        for r in rows.tolist():  # refresh LRU order, then insert the new rows
            if r in cache:
                cache.move_to_end(r)
        cache.update(fresh)
        while len(cache) > self.cache_size:
            cache.popitem(last=False)
        R3 = self.grid_resolution ** 3
        if not out:
            return np.zeros((0, R3, self.channels), np.float32), np.zeros((0, R3), np.float32)
        return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])

    def _read_rows(self, rows: np.ndarray):
        """Read sorted landmark rows: contiguous runs are read with one slice each."""
        dd = self._f["voxels/descriptors"]
        ds = self._f["voxels/density"]
        R3 = self.grid_resolution ** 3
        out_d = np.empty((len(rows), R3, self.channels), np.float32)
        out_s = np.empty((len(rows), R3), np.float32)
        breaks = np.flatnonzero(np.diff(rows) != 1) + 1
        try:
            for run in np.split(np.arange(len(rows)), breaks):
                a, b = int(rows[run[0]]), int(rows[run[-1]]) + 1
                out_d[run] = dd[a:b].reshape(b - a, R3, self.channels)
                out_s[run] = ds[a:b].reshape(b - a, R3)
                self.bytes_read += (b - a) * R3 * (self.channels * dd.dtype.itemsize + ds.dtype.itemsize)
        except OSError as e:
            raise MapFormatError(f"{self.path}: voxel data is corrupted (checksum or read error: {str(e).splitlines()[0]})") from None
        return out_d, out_s

    def mean_descriptors(self, rows) -> np.ndarray:
        rows = np.asarray(rows, np.int64)
        order = np.argsort(rows)
        out = np.empty((len(rows), self.channels), np.float32)
        try:
            out[order] = self._f["landmarks/mean_descriptor"][rows[order]] if len(rows) else out
        except (OSError, TypeError) as e:
            raise MapFormatError(f"{self.path}: corrupted mean descriptors ({e})") from None
        return out

    def tracks(self):
        g = self._f["tracks"]
        return g["landmark_index"][()], g["frame_index"][()], g["xy"][()]

    def load(self) -> MapData:
        """Everything in memory (for merge/prune/export of small maps)."""
        R = self.grid_resolution
        try:
            vd = self._f["voxels/descriptors"][()].astype(np.float32)
            vs = self._f["voxels/density"][()].astype(np.float32)
            md = self._f["landmarks/mean_descriptor"][()].astype(np.float32)
        except OSError as e:
            raise MapFormatError(f"{self.path}: voxel data is corrupted ({str(e).splitlines()[0]})") from None
        tl, tf, txy = self.tracks()
        return MapData(
            extractor=self.extractor, channels=self.channels, grid_resolution=R, patch_size=self.patch_size,
            render_samples=self.render_samples, max_side=self.max_side, ids=self.ids, positions=self.positions,
            voxel_size=self.voxel_size, track_length=self.track_length, reproj_error=self.reproj_error,
            quality=self.quality, cosine=self.cosine, view_dir=self.view_dir, view_angle=self.view_angle,
            depth_range=self.depth_range, mean_descriptor=md, descriptors=vd, density=vs, cameras=dict(self.cameras),
            frame_names=list(self.frame_names), frame_camera_ids=self.frame_camera_ids, cam_from_world=self.cam_from_world,
            track_landmark=tl, track_frame=tf, track_xy=txy, provenance=dict(self.provenance))
