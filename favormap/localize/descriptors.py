"""Where the localizer's landmark descriptors come from (one small plugin interface).

A descriptor source turns landmark rows and the current pose estimate into unit descriptors:

- ``rendered``: FaVoR, rendered from each landmark's voxel grids along the ray from the camera
  centre (paper sec. 3.3);
- ``mean``: the landmark's mean observed descriptor (baseline: what a structure-based map stores);
- ``nearest``: the descriptor observed in the mapping frame whose camera centre is nearest the
  current estimate (baseline: the best a map of stored descriptors could do without rendering). It
  needs the per-observation descriptors, which the map does not store; :func:`observation_descriptors`
  computes them from the mapping images.

A user's source may return several descriptors per landmark (k len(rows) rows, block by block);
:func:`describe` then names each descriptor's landmark. A source that says ``one_per_landmark = True``
lets the localizer keep a landmark's descriptor through one query while the camera sees it along
nearly the same ray (:class:`SeenRays`, ``LocalizeConfig.rerender_angle_deg``).
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from ..geometry import camera_centers
from ..mapfile import Map


class DescriptorSource(Protocol):
    name: str

    def __call__(self, rows: np.ndarray, cam_from_world: np.ndarray, timings: dict) -> np.ndarray:
        """Unit descriptors (len(rows), C) float32 of landmark ``rows`` seen from ``cam_from_world``."""


def unit_rows(x) -> np.ndarray:
    """Rows scaled to unit L2 norm (float32; all-zero rows stay zero)."""
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def _tick(timings: dict, key: str, since: float) -> float:
    now = time.perf_counter()
    timings[key] = timings.get(key, 0.0) + now - since
    return now


class RenderedDescriptors:
    """FaVoR: rendered from each landmark's voxel grids. On the CPU with NumPy
    (:mod:`favormap.voxels.render_numpy`: the localizer does not import torch, which takes ~2 s to
    import); on another ``device`` with torch.

    On the CPU the landmarks are read and rendered ``chunk`` at a time: the grids of a chunk (~7 MB for
    512 landmarks) come from the allocator's free lists and stay in the CPU caches for the rendering,
    where the grids of all visible landmarks at once (~80 MB for the 6,000 of a real query) are a fresh
    mapping of memory on every call; each landmark's descriptor is the same either way."""

    name = "rendered"
    one_per_landmark = True  # SeenRays may keep its descriptors within a query
    chunk = 512

    def __init__(self, map_: Map, device: str = "cpu"):
        self.map, self.device = map_, device

    def __call__(self, rows, cam_from_world, timings):
        centre = np.asarray(camera_centers(cam_from_world), np.float32)
        if self.device != "cpu":
            return self._render_torch(rows, centre, timings)
        from ..voxels.render_numpy import render_from_camera_numpy

        out = np.empty((len(rows), self.map.channels), np.float32)
        for a in range(0, len(rows), self.chunk):
            s = time.perf_counter()
            part = rows[a : a + self.chunk]
            desc, dens = self.map.voxels(part)
            s = _tick(timings, "loading", s)
            out[a : a + len(part)] = render_from_camera_numpy(
                desc, dens, *self._geometry(part), centre, self.map.render_samples
            )
            _tick(timings, "rendering", s)
        return out

    def _geometry(self, rows):
        return np.asarray(self.map.positions[rows], np.float32), np.asarray(self.map.voxel_size[rows], np.float32)

    def _render_torch(self, rows, centre, timings):
        import torch

        from ..voxels.render import render_from_camera

        s = time.perf_counter()
        desc, dens = self.map.voxels(rows)
        s = _tick(timings, "loading", s)
        args = (np.asarray(desc, np.float32), np.asarray(dens, np.float32), *self._geometry(rows), centre)
        with torch.no_grad():
            out = render_from_camera(*(torch.as_tensor(a, device=self.device) for a in args), self.map.render_samples)
        out = out.cpu().numpy()
        _tick(timings, "rendering", s)
        return out


class MeanDescriptors:
    name = "mean"
    one_per_landmark = True  # SeenRays may keep its descriptors within a query

    def __init__(self, map_: Map):
        self.map = map_

    def __call__(self, rows, cam_from_world, timings):
        s = time.perf_counter()
        d = unit_rows(self.map.mean_descriptors(rows))
        _tick(timings, "loading", s)
        return d


class NearestViewDescriptors:
    """The observed descriptor from the mapping frame nearest to the current estimate."""

    name = "nearest"
    one_per_landmark = True  # SeenRays may keep its descriptors within a query

    def __init__(self, map_: Map, obs_descriptors: np.ndarray):
        from .observations import ObservationIndex

        self.index = ObservationIndex(map_)
        if len(obs_descriptors) != len(self.index.order):
            raise ValueError(f"{len(obs_descriptors)} observation descriptors for {len(self.index.order)} observations")
        self.obs_desc = np.ascontiguousarray(obs_descriptors[self.index.order], np.float32)

    def __call__(self, rows, cam_from_world, timings):
        s = time.perf_counter()
        ix, center = self.index, camera_centers(cam_from_world)
        best = ix.best(rows, lambda obs, _: np.linalg.norm(ix.centers[ix.frame[obs]] - center, axis=1))
        out = np.zeros((len(best), self.obs_desc.shape[1]), np.float32)
        out[best >= 0] = self.obs_desc[best[best >= 0]]
        _tick(timings, "loading", s)
        return unit_rows(out)


def observation_descriptors(map_: Map, sequence, extractor=None) -> np.ndarray:
    """(O, C) descriptors of every track observation of ``map_``, sampled at the observed keypoint
    in the mapping images of ``sequence`` (the sequence the map was built from)."""
    from .. import features as feats_mod
    from ..io import load_image

    names = {f.name: i for i, f in enumerate(sequence.frames)}
    missing = [n for n in map_.frame_names if n not in names]
    if missing:
        raise ValueError(f"{len(missing)} map frames are not in the sequence (e.g. {missing[0]})")
    ex = extractor or feats_mod.create(map_.extractor)
    lm, fr, xy = map_.tracks()
    out = np.zeros((len(lm), map_.channels), np.float32)
    for f in np.unique(fr):
        frame = sequence.frames[names[map_.frame_names[f]]]
        img, _ = load_image(frame.image_path, sequence.cameras[frame.camera_id], map_.max_side)
        sel = np.flatnonzero(fr == f)
        out[sel] = ex.sample(ex.extract(img), xy[sel])
    return out


def describe(
    source: DescriptorSource, rows: np.ndarray, cam_from_world: np.ndarray, timings: dict, seen: SeenRays | None = None
):
    """(descriptors, their landmark rows): ``source``'s descriptors of ``rows`` and, per descriptor,
    its landmark (``rows`` itself for a source with one descriptor per landmark; repeated for a
    source that returns several per landmark, block by block). With ``seen`` (one query's), a landmark
    seen along nearly the ray it was described for earlier in the query keeps that descriptor."""
    rows = np.asarray(rows, np.int64)
    if seen is not None and len(rows):
        return seen.describe(source, rows, cam_from_world, timings), rows
    d = source(rows, cam_from_world, timings)
    if len(rows) == 0 or len(d) == len(rows):
        return d, rows
    return d, np.tile(rows, len(d) // len(rows))


class SeenRays:
    """The descriptors one query's localization got from a source with one descriptor per landmark, by
    landmark, with the direction of the ray each was computed along. A landmark asked for again from a
    camera centre that sees it within ``max_angle_deg`` of that ray keeps its descriptor: the rendering
    iterations and the guided step ask for mostly the same landmarks from estimates millimetres apart,
    where a rendering changes by far less than the descriptors' own view dependence (the grids interpolate
    the training views, degrees apart)."""

    def __init__(self, positions: np.ndarray, max_angle_deg: float):
        self.positions = positions
        self.min_cos = float(np.cos(np.radians(max_angle_deg)))
        # the landmarks described so far (sorted) and each one's slot in ``desc`` / ``dirs``: a landmark described
        # again overwrites its slot, a new one takes the next, so storing never moves the descriptors kept
        self.rows = np.zeros(0, np.int64)
        self.slots = np.zeros(0, np.int64)
        self.desc: np.ndarray | None = None  # (capacity, C)
        self.dirs = np.zeros((0, 3), np.float32)
        self.size = 0  # slots in use

    def describe(self, source: DescriptorSource, rows: np.ndarray, cam_from_world: np.ndarray, timings: dict):
        kept, kept_slots, fresh, dirs = self.split(rows, cam_from_world)
        d = source(rows[fresh], cam_from_world, timings)
        if len(d) != len(fresh):
            raise ValueError(f"descriptor source {getattr(source, 'name', source)!r} gives several per landmark")
        out = np.empty((len(rows), d.shape[1] if len(fresh) else self.desc.shape[1]), np.float32)
        out[fresh] = d
        if len(kept):
            out[kept] = self.desc[kept_slots]
        self.store(rows[fresh], d, dirs[fresh])
        return out

    def split(self, rows: np.ndarray, cam_from_world: np.ndarray):
        """(positions in ``rows`` (sorted) of the landmarks that keep their descriptor, their slots in ``desc``,
        positions of those to describe again, every row's unit ray direction): a caller that describes the
        latter itself hands them to :meth:`store`."""
        dirs = np.asarray(self.positions[rows], np.float32) - np.asarray(camera_centers(cam_from_world), np.float32)
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
        known, slots = self._find(rows)
        keep = known.copy()
        keep[known] = np.einsum("ij,ij->i", dirs[known], self.dirs[slots]) >= self.min_cos
        return np.flatnonzero(keep), slots[keep[known]], np.flatnonzero(~keep), dirs

    def _find(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(which of ``rows`` were described before, the slots of those)."""
        at = np.minimum(np.searchsorted(self.rows, rows), max(len(self.rows) - 1, 0))
        known = (self.rows[at] == rows) if len(self.rows) else np.zeros(len(rows), bool)
        return known, self.slots[at[known]]

    def store(self, rows: np.ndarray, desc: np.ndarray, dirs: np.ndarray) -> None:
        """Keep the descriptors ``desc`` of landmarks ``rows`` (sorted, unique), computed along the unit rays
        ``dirs``."""
        if len(rows) == 0:
            return
        known, known_slots = self._find(rows)
        slots = np.empty(len(rows), np.int64)
        slots[known] = known_slots
        new = np.flatnonzero(~known)
        slots[new] = self.size + np.arange(len(new))
        self.size += len(new)
        if self.desc is None or self.size > len(self.desc):
            cap = max(2 * self.size, 1024)
            grown = np.empty((cap, desc.shape[1]), np.float32)
            grown_dirs = np.empty((cap, 3), np.float32)
            if self.desc is not None:
                grown[: len(self.desc)], grown_dirs[: len(self.desc)] = self.desc, self.dirs
            self.desc, self.dirs = grown, grown_dirs
        self.desc[slots], self.dirs[slots] = desc, dirs
        ins = np.searchsorted(self.rows, rows[new])
        self.rows = np.insert(self.rows, ins, rows[new])
        self.slots = np.insert(self.slots, ins, slots[new])


def make_source(
    name: str, map_: Map, device: str = "cpu", obs_descriptors: np.ndarray | None = None
) -> DescriptorSource:
    """A descriptor source by name: rendered, mean or nearest."""
    if name == "rendered":
        return RenderedDescriptors(map_, device)
    if name == "mean":
        return MeanDescriptors(map_)
    if name == "nearest":
        if obs_descriptors is None:
            raise ValueError("nearest-view descriptors need the observation descriptors (observation_descriptors())")
        return NearestViewDescriptors(map_, obs_descriptors)
    raise ValueError(f"unknown descriptor source {name!r} (rendered, mean, nearest)")
