"""The on-disk feature cache: every frame's features in one HDF5 file, read back one frame at a time.

A build holds a frame's features (keypoints, descriptors and the extractor's sampling state) only
while it works on that frame, so its memory grows with the number of landmarks, not with frames x
keypoints (hloc keeps its features in HDF5 files for the same reason). A named cache file is kept
and reused: a later build with the same extractor settings extracts only the images the file does
not hold yet (new images, changed image files, images an interrupted build did not reach). Entries
are keyed by the image file's absolute path, so frames that share an image share its entry.

Layout (``favormap-features`` version 1)::

    /                     attrs: format, version, extractor, max_keypoints, max_side
    /frames/<path>        one group per image (its absolute path, "/" escaped), attrs:
                          name (the path), source_size, source_mtime_ns (the image file's), image_size,
                          camera_model, camera_width, camera_height, camera_params (working camera),
                          complete (written last: a frame without it is extracted again)
        keypoints (N, 2) float32, scores (N,) float32, descriptors (N, C) float32
        state/<key>       the extractor's sampling state (Extractor.state_arrays)

Descriptors are stored as float32, so that a build from the cache is the same map as one in memory;
every dataset carries a Fletcher-32 checksum, so that a damaged file is an error, not wrong features.
"""

from __future__ import annotations

import os
from collections.abc import Sequence as SequenceABC
from pathlib import Path

import h5py
import numpy as np

from ..errors import InputError
from ..io.types import Camera
from .base import Features, extractor_class

FORMAT, VERSION = "favormap-features", 1


def _key(name: str) -> str:
    return name.replace("%", "%25").replace("/", "%2F")


def source_stamp(path) -> tuple[int, int]:
    """(size, mtime_ns) of an image file: a cached frame is reused only while these are unchanged
    (a missing or unreadable file is an InputError naming it, as when its bytes are read)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"image not found: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read image {path}: {e.strerror or e}") from None
    return int(st.st_size), int(st.st_mtime_ns)


class FeatureCache:
    """An HDF5 feature cache for one extractor setting (``extractor``, ``max_keypoints``,
    ``max_side``). Opening a file written with other settings is an error (name another file or
    delete it); so is a file that is not a favormap feature cache."""

    def __init__(self, path, extractor: str, max_keypoints: int, max_side: int):
        self.path = Path(path)
        self.extractor = extractor
        self.cls = extractor_class(extractor)
        if not self.cls.can_cache():
            raise InputError(f"extractor {extractor!r} cannot keep its features in a feature cache")
        settings = {"extractor": extractor, "max_keypoints": int(max_keypoints), "max_side": int(max_side)}
        if self.path.exists() and not (self.path.is_file() and h5py.is_hdf5(self.path)):
            raise InputError(f"{self.path} exists and is not a favormap feature cache")
        try:
            self.file = h5py.File(self.path, "a")
        except OSError as e:
            why = os.strerror(e.errno) if e.errno else str(e)
            raise InputError(f"cannot open the feature cache {self.path}: {why}") from None
        try:
            f = self.file
            if not len(f.attrs) and not len(f):
                f.attrs.update({"format": FORMAT, "version": VERSION, **settings})
                f.create_group("frames")
            elif f.attrs.get("format") != FORMAT or "frames" not in f:
                raise InputError(f"{self.path} is not a favormap feature cache")
            elif int(f.attrs.get("version", -1)) != VERSION:
                raise InputError(f"feature cache {self.path} has version {f.attrs.get('version')}, not {VERSION}")
            else:
                stored = {k: f.attrs.get(k) for k in settings}
                stored = {k: (v.item() if hasattr(v, "item") else v) for k, v in stored.items()}
                if stored != settings:
                    diff = ", ".join(f"{k} {stored[k]!r} (not {v!r})" for k, v in settings.items() if stored[k] != v)
                    raise InputError(
                        f"feature cache {self.path} was made with other settings: {diff}; "
                        "delete it or name another file"
                    )
        except BaseException:
            self.file.close()
            raise
        self.frames = self.file["frames"]

    # -- writing --------------------------------------------------------------------------------
    def has(self, name: str, stamp: tuple[int, int] | None = None) -> bool:
        """Whether frame ``name`` is complete in the cache (and, given ``stamp``, from that file)."""
        g = self.frames.get(_key(name))
        if g is None or not g.attrs.get("complete", False):
            return False
        return stamp is None or (int(g.attrs["source_size"]), int(g.attrs["source_mtime_ns"])) == tuple(stamp)

    def put(self, name: str, features: Features, camera: Camera, stamp: tuple[int, int]) -> None:
        key = _key(name)
        if key in self.frames:
            del self.frames[key]
        g = self.frames.create_group(key)
        arrays = {
            "keypoints": np.asarray(features.keypoints, np.float32).reshape(-1, 2),
            "scores": np.asarray(features.scores, np.float32).reshape(-1),
            "descriptors": np.asarray(features.descriptors, np.float32),
            **{f"state/{k}": np.asarray(v) for k, v in self.cls.state_arrays(features.dense).items()},
        }
        for k, v in arrays.items():  # Fletcher-32 checksums: a damaged file is an error, not wrong features
            g.create_dataset(k, data=v, fletcher32=v.size > 0)
        g.attrs.update(
            {
                "name": name,
                "source_size": stamp[0],
                "source_mtime_ns": stamp[1],
                "image_size": np.asarray(features.image_size, np.int64),
                "camera_model": camera.model,
                "camera_width": camera.width,
                "camera_height": camera.height,
                "camera_params": np.asarray(camera.params, np.float64),
            }
        )
        g.attrs["complete"] = True
        self.file.flush()

    # -- reading --------------------------------------------------------------------------------
    def _group(self, name: str):
        g = self.frames.get(_key(name))
        if g is None or not g.attrs.get("complete", False):
            raise InputError(f"feature cache {self.path} has no features of frame {name!r}")
        return g

    def camera(self, name: str) -> Camera:
        a = self._group(name).attrs
        return Camera(str(a["camera_model"]), int(a["camera_width"]), int(a["camera_height"]), a["camera_params"])

    def count(self, name: str) -> int:
        return int(self._group(name)["keypoints"].shape[0])

    def get(self, name: str, state: bool = True) -> Features:
        """The features of frame ``name``; ``state``: with the sampling state (``Features.dense``)."""
        g = self._group(name)
        try:
            dense = self.cls.state_from_arrays({k: v[()] for k, v in g["state"].items()}) if state else None
            w, h = (int(v) for v in g.attrs["image_size"])
            return Features(g["keypoints"][()], g["scores"][()], g["descriptors"][()], (w, h), dense)
        except (OSError, KeyError, ValueError) as e:
            raise InputError(
                f"feature cache {self.path} is damaged (frame {name}: {e}); delete it or name another file"
            ) from None

    def view(self, names: list[str], state: bool = True) -> CachedFrames:
        return CachedFrames(self, list(names), state)

    def close(self) -> None:
        if self.file.id.valid:
            self.file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class CachedFrames(SequenceABC):
    """The features of a list of frames, read from a :class:`FeatureCache` on access (a list of
    :class:`Features` to the code that uses it; nothing is kept in memory)."""

    def __init__(self, cache: FeatureCache, names: list[str], state: bool = True):
        self.cache, self.names, self.state = cache, names, state

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return self.cache.get(self.names[i], self.state)

    def counts(self) -> np.ndarray:
        """Keypoints per frame, without reading the features."""
        return np.array([self.cache.count(n) for n in self.names], np.int64)

    def without_state(self) -> CachedFrames:
        """The same frames, read without the sampling state (what tracking needs: cheaper)."""
        return CachedFrames(self.cache, self.names, False)
