"""Writing a map from parts of other maps (the map operations merge and prune): the per-landmark
metadata, the cameras, frames and tracks, and the bulk per-landmark datasets streamed batch by batch."""

from __future__ import annotations

import numpy as np

from ..mapfile.fields import bulk_datasets, field_name, metadata_datasets
from ..mapfile.writer import MapWriter, camera_arrays

_VOXEL_GRIDS = ("voxels/descriptors", "voxels/density")  # streamed through Map.voxels (cached, resampled)


def write_landmark_metadata(w: MapWriter, arrays: dict) -> None:
    """Every per-landmark metadata dataset of the schema, from ``arrays`` keyed by field name."""
    for p in metadata_datasets():
        w.put(p, arrays[field_name(p)])


def write_frames_and_tracks(
    w: MapWriter,
    cameras: dict,
    names,
    camera_ids,
    cam_from_world,
    track_landmark,
    track_frame,
    track_xy,
    track_patch=None,
    cam_from_rig=None,
) -> None:
    """The cameras/*, frames/* and tracks/* datasets (``track_patch``: the optional tracks/patch,
    ``cam_from_rig``: the optional frames/cam_from_rig)."""
    for name, arr in camera_arrays(cameras).items():
        w.put(name, arr)
    w.put("frames/names", names)
    w.put("frames/camera_ids", camera_ids)
    w.put("frames/cam_from_world", cam_from_world)
    if cam_from_rig is not None:
        w.put("frames/cam_from_rig", np.asarray(cam_from_rig, np.float64))
    w.put("tracks/landmark_index", track_landmark)
    w.put("tracks/frame_index", track_frame)
    w.put("tracks/xy", track_xy)
    if track_patch is not None:
        w.put("tracks/patch", track_patch)


def copy_voxels(w: MapWriter, sources, chunk: int = 4096, resample: dict | None = None, progress=None) -> None:
    """Stream the bulk per-landmark datasets (voxel grids, mean descriptors, ...) into ``w``:
    ``sources`` is a list of (map, rows) segments in output order; ``resample`` maps a segment index
    to an (R^3, R^3) node matrix applied to the voxel grids."""
    resample = resample or {}
    others = [p for p in bulk_datasets() if p not in _VOXEL_GRIDS]
    for p in (*_VOXEL_GRIDS, *others):
        w.create(p)
    out = 0
    total = sum(len(r) for _, r in sources)
    for si, (m, rows) in enumerate(sources):
        rows = np.asarray(rows, np.int64)
        W = resample.get(si)
        for a in range(0, len(rows), chunk):
            r = rows[a : a + chunk]
            d, s = m.voxels(r)
            if W is not None:
                d = np.einsum("nr,brc->bnc", W, d, optimize=True)
                s = s @ W.T
            w.write_rows("voxels/descriptors", out, d)
            w.write_rows("voxels/density", out, s)
            for p in others:
                w.write_rows(p, out, m.landmark_rows(p, r))
            out += len(r)
            if progress:
                progress("voxels", out, total)
