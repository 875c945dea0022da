"""Landmark queries on an opened map: visible from a pose, or near a point (radius / k-NN)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers
from ..io import Camera, working_camera
from .spatial import SpatialIndex, ViewLimits, occluded, visible_rows


def default_camera(m) -> Camera:
    """The map's first camera, undistorted and resized like the build did (its working camera)."""
    if not m.cameras:
        raise InputError("the map has no cameras; give --camera")
    return working_camera(m.cameras[sorted(m.cameras)[0]], m.max_side)


def map_index(m) -> SpatialIndex:
    """A SpatialIndex over the map's positions, built once per map object."""
    idx = getattr(m, "_favormap_spatial_index", None)
    if idx is None or len(idx) != len(m.positions):
        idx = SpatialIndex(m.positions, backend="open3d")
        try:
            m._favormap_spatial_index = idx
        except AttributeError:
            pass
    return idx


@dataclass
class QueryResult:
    mode: str  # "pose" or "near"
    rows: np.ndarray  # landmark rows (sorted for pose queries, nearest first for k-NN)
    ids: np.ndarray  # uint64 ids of those rows
    num_landmarks: int
    distances: np.ndarray | None = None
    counts: dict = field(default_factory=dict)
    camera: Camera | None = None
    camera_center: np.ndarray | None = None

    def to_dict(self) -> dict:
        d = {"mode": self.mode, "num_landmarks": self.num_landmarks, **self.counts}
        if self.mode == "pose":
            d["num_visible"] = int(len(self.rows))
            d["visible_ids"] = [int(i) for i in self.ids]
            d["visible_rows"] = self.rows.tolist()
            d["camera_center"] = self.camera_center.tolist()
            d["camera"] = self.camera.to_dict()
        else:
            d["count"] = int(len(self.rows))
            d["ids"] = [int(i) for i in self.ids]
            d["rows"] = self.rows.tolist()
            d["distances"] = [float(x) for x in self.distances]
        return d


def query_pose(
    m,
    cam_from_world: np.ndarray,
    camera: Camera | None = None,
    mesh=None,
    limits: ViewLimits | None = None,
    index: SpatialIndex | None = None,
) -> QueryResult:
    """Landmarks of ``m`` (Map or MapData) visible from ``cam_from_world``: frustum, trained depth
    and viewing-angle ranges (``spatial.visible_rows``), and with a ``mesh`` not occluded by it."""
    cam = default_camera(m) if camera is None else working_camera(camera, m.max_side)
    index = map_index(m) if index is None else index
    c = camera_centers(np.asarray(cam_from_world, np.float64))
    limits = ViewLimits() if limits is None else limits
    rows = visible_rows(index, cam, cam_from_world, m.view_dir, m.view_angle, m.depth_range, limits)
    reach = float(np.max(m.depth_range[:, 1])) * limits.depth_scale[1] if len(index) else 0.0
    in_frustum = len(index.frustum(cam, cam_from_world, reach)) if len(index) else 0  # within the largest reach
    counts = {"num_in_frustum": in_frustum, "num_view_ok": int(len(rows)), "num_occluded": 0}
    if mesh is not None and len(rows):
        hid = occluded(index.positions[rows], c, mesh, tolerance=0.5 * np.asarray(m.voxel_size, np.float64)[rows])
        counts["num_occluded"] = int(hid.sum())
        rows = rows[~hid]
    return QueryResult("pose", rows, np.asarray(m.ids)[rows], len(index), None, counts, cam, c)


def query_near(
    m, center, radius: float | None = None, knn: int | None = None, index: SpatialIndex | None = None
) -> QueryResult:
    """Landmarks within ``radius`` of ``center`` (sorted by distance), or its ``knn`` nearest."""
    center = np.asarray(center, np.float64).reshape(3)
    if not np.all(np.isfinite(center)):
        raise InputError("--near needs three finite coordinates")
    if (radius is None) == (knn is None):
        raise InputError("give exactly one of --radius R or --knn K with --near")
    index = map_index(m) if index is None else index
    if radius is not None:
        if not (radius >= 0 and np.isfinite(radius)):
            raise InputError(f"--radius must be a finite number >= 0, got {radius}")
        rows = index.radius(center, radius)
        d = np.linalg.norm(index.positions[rows] - center, axis=1)
        o = np.argsort(d, kind="stable")
        rows, d = rows[o], d[o]
    else:
        if knn < 1:
            raise InputError(f"--knn must be >= 1, got {knn}")
        rows, d = index.knn(center, knn)
    return QueryResult("near", rows, np.asarray(m.ids)[rows], len(index), d, {}, None, center)
