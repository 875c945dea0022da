"""Spatial index over landmark positions (Open3D KD-tree), shared by localize, query, merge and
prune: radius, k-NN and frustum queries, plus an optional occlusion test by raycasting a mesh.

Frustum and visibility queries are exact: the KD-tree only gathers candidates inside a sphere that
encloses the frustum, and the candidates then go through the same projection / depth / viewing-angle
tests a brute-force scan would apply (``visible_mask``), so the result equals the brute-force one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..geometry import camera_centers
from ..io import Camera


@dataclass
class ViewLimits:
    """How far a query view may stray from the views a landmark was trained on."""

    angle_margin_deg: float = 15.0  # on top of the landmark's own training view-angle radius
    depth_scale: tuple[float, float] = (0.5, 2.0)  # allowed distance range, relative to the training range
    image_margin_px: float = 0.0  # keep landmarks projecting at least this far inside the image


# Landmarks whose reach (max training distance x depth_scale) is above this quantile of all reaches
# are not looked up through the KD-tree but tested directly, so that a few landmarks seen from far
# away do not blow up the frustum's bounding sphere for every query.
_REACH_QUANTILE = 0.99


class SpatialIndex:
    """Open3D KD-tree over (L, 3) positions."""

    def __init__(self, positions: np.ndarray):
        self.positions = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
        self._tree = None
        self._nns = None
        self._reach_cache = None
        if len(self.positions):
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.positions))
            self._tree = o3d.geometry.KDTreeFlann(pcd)

    def __len__(self) -> int:
        return len(self.positions)

    # -- single queries (Open3D KDTreeFlann) ----------------------------------------------------
    def radius(self, center, r: float) -> np.ndarray:
        """Rows within distance ``r`` of ``center`` (sorted)."""
        if self._tree is None or not r >= 0:
            return np.zeros(0, np.int64)
        if not np.isfinite(r):
            return np.arange(len(self), dtype=np.int64)
        _, idx, _ = self._tree.search_radius_vector_3d(np.asarray(center, np.float64).reshape(3), float(r))
        return np.sort(np.asarray(idx, np.int64))

    def knn(self, center, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows and distances of the ``k`` nearest landmarks (nearest first)."""
        if self._tree is None or k <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        n, idx, d2 = self._tree.search_knn_vector_3d(np.asarray(center, np.float64).reshape(3), int(min(k, len(self))))
        return np.asarray(idx, np.int64), np.sqrt(np.asarray(d2))

    # -- batched queries (Open3D core NearestNeighborSearch) ------------------------------------
    def knn_batch(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, k) rows and distances of the ``k`` nearest landmarks of each query point, nearest
        first; rows are -1 and distances inf where the index has fewer than ``k`` points."""
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        rows = np.full((len(points), max(k, 0)), -1, np.int64)
        dist = np.full((len(points), max(k, 0)), np.inf)
        kk = min(k, len(self))
        if kk <= 0 or len(points) == 0:
            return rows, dist
        if self._nns is None:
            self._nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(self.positions))
            self._nns.knn_index()
        idx, d2 = self._nns.knn_search(o3d.core.Tensor(points), kk)
        rows[:, :kk] = idx.numpy().reshape(len(points), kk)
        dist[:, :kk] = np.sqrt(np.maximum(d2.numpy().reshape(len(points), kk), 0))
        return rows, dist

    # -- frustum ------------------------------------------------------------------------------
    def frustum(self, camera: Camera, cam_from_world: np.ndarray, max_depth: float, min_depth: float = 0.0) -> np.ndarray:
        """Rows (sorted) of landmarks inside the pinhole camera's frustum between ``min_depth`` and
        ``max_depth`` (z in the camera frame): a KD-tree radius query around a sphere enclosing the
        frustum, then an exact projection test on the candidates."""
        if self._tree is None:
            return np.zeros(0, np.int64)
        if not np.isfinite(max_depth):
            cand = np.arange(len(self), dtype=np.int64)
        else:
            center, r = frustum_sphere(camera, cam_from_world, max_depth, min_depth)
            cand = self.radius(center, r * (1 + 1e-9) + 1e-12)
        return cand[project_inside(self.positions[cand], camera, cam_from_world, min_depth, max_depth)]


def frustum_sphere(camera: Camera, cam_from_world: np.ndarray, max_depth: float, min_depth: float = 0.0) -> tuple[np.ndarray, float]:
    """A small sphere (centre, radius) enclosing the frustum between ``min_depth`` and ``max_depth``.

    The frustum is the convex hull of its near and far corners (the near ones collapse to the
    camera centre when ``min_depth`` is 0), so any sphere holding the corners holds it. The centre
    is searched on the segment between the near and far corner centroids, where the radius (the
    farthest corner) is a convex function of the position."""
    K = camera.K
    corners_px = np.array([[0, 0], [camera.width, 0], [0, camera.height], [camera.width, camera.height]], float)
    rays = np.c_[(corners_px - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(4)]
    wfc_R = cam_from_world[:3, :3].T
    c = camera_centers(cam_from_world)
    far = (rays * max_depth) @ wfc_R.T + c
    near = (rays * max(min_depth, 0.0)) @ wfc_R.T + c
    pts = np.vstack([far, near])
    a, b = near.mean(0), far.mean(0)
    s = np.linspace(0.0, 1.0, 257)
    centers = a + s[:, None] * (b - a)
    radii = np.linalg.norm(pts[None] - centers[:, None], axis=2).max(1)
    i = int(np.argmin(radii))
    return centers[i], float(radii[i])


def project_inside(points: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_depth=0.0, max_depth=np.inf, margin_px=0.0) -> np.ndarray:
    """Mask of points in front of a pinhole camera, inside its image and depth range."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    Xc = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = Xc[:, 2]
    ok = (z > max(min_depth, 1e-9)) & (z <= max_depth)
    zs = np.where(ok, z, 1.0)
    K = camera.K
    u = K[0, 0] * Xc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / zs + K[1, 2]
    return ok & (u >= margin_px) & (u <= camera.width - margin_px) & (v >= margin_px) & (v <= camera.height - margin_px)


def visible_mask(positions: np.ndarray, camera: Camera, cam_from_world: np.ndarray, view_dir: np.ndarray,
                 view_angle: np.ndarray, depth_range: np.ndarray, limits: ViewLimits = ViewLimits()) -> np.ndarray:
    """The exact visibility test of :func:`visible_rows` on explicit arrays (no index): in front of
    the camera, inside the image (with the margin), within the distance range and the viewing-angle
    range each landmark was trained for."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    ok = project_inside(positions, camera, cam_from_world, margin_px=max(limits.image_margin_px, 0.0))
    c = camera_centers(cam_from_world)
    v = c - positions
    dist = np.linalg.norm(v, axis=1)
    cosang = np.sum(v * np.asarray(view_dir, np.float64), 1) / np.maximum(dist, 1e-12)
    ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    dr = np.asarray(depth_range, np.float64)
    ok &= ang <= np.asarray(view_angle, np.float64) + limits.angle_margin_deg
    ok &= (dist >= dr[:, 0] * limits.depth_scale[0]) & (dist <= dr[:, 1] * limits.depth_scale[1])
    return ok


def _reach_split(index: SpatialIndex, depth_range: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """(cap, far rows): most landmarks are reachable within ``cap``; the others are tested directly.
    Cached on the index for the same depth_range array and scale."""
    cache = index._reach_cache
    if cache is not None and cache[0] is depth_range and cache[1] == scale and cache[2] == depth_range.shape:
        return cache[3], cache[4]
    reach = np.asarray(depth_range[:, 1], np.float64) * scale
    if len(reach) > 1000:
        cap = float(np.quantile(reach, _REACH_QUANTILE))
        far = np.flatnonzero(reach > cap)
    else:
        cap, far = float(reach.max()), np.zeros(0, np.int64)
    index._reach_cache = (depth_range, scale, depth_range.shape, cap, far)  # keeps depth_range alive: id stays valid
    return cap, far


def visible_rows(index: SpatialIndex, camera: Camera, cam_from_world: np.ndarray, view_dir: np.ndarray,
                 view_angle: np.ndarray, depth_range: np.ndarray, limits: ViewLimits = ViewLimits()) -> np.ndarray:
    """Landmarks visible from a pose: in the frustum, within the distance range and the viewing
    angle range they were trained for (paper sec. 3.3). Returns sorted rows; equal to
    ``flatnonzero(visible_mask(all positions, ...))``."""
    if len(index) == 0:
        return np.zeros(0, np.int64)
    depth_range = np.asarray(depth_range)
    cap, far = _reach_split(index, depth_range, float(limits.depth_scale[1]))
    rows = index.frustum(camera, cam_from_world, cap)
    if len(far):
        rows = np.union1d(rows, far)
    ok = visible_mask(index.positions[rows], camera, cam_from_world, view_dir[rows], view_angle[rows], depth_range[rows], limits)
    return rows[ok]


# -- occlusion ------------------------------------------------------------------------------------
def make_raycaster(mesh) -> o3d.t.geometry.RaycastingScene:
    """An Open3D RaycastingScene of a trimesh.Trimesh / trimesh.Scene or an Open3D triangle mesh."""
    if isinstance(mesh, o3d.t.geometry.RaycastingScene):
        return mesh
    if not isinstance(mesh, o3d.t.geometry.TriangleMesh):
        if isinstance(mesh, o3d.geometry.TriangleMesh):
            mesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
        else:  # trimesh
            if hasattr(mesh, "geometry") and hasattr(mesh, "to_geometry"):  # trimesh.Scene
                mesh = mesh.to_geometry()
            faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int32).reshape(-1, 3)
            tm = o3d.t.geometry.TriangleMesh()
            tm.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, np.float32))
            tm.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(faces))
            mesh = tm
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    return scene


def occluded(points: np.ndarray, camera_center: np.ndarray, mesh, tolerance=1e-3) -> np.ndarray:
    """Mask of points hidden from ``camera_center`` by ``mesh`` (a trimesh.Trimesh/Scene, an Open3D
    TriangleMesh or a prebuilt RaycastingScene), by casting a ray to every point. A point counts as
    hidden when the first hit is more than ``tolerance`` (scalar or per point, scene units; plus
    0.1 % of the distance) in front of it, so landmarks on the surface itself stay visible."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, bool)
    scene = make_raycaster(mesh)
    camera_center = np.asarray(camera_center, np.float64).reshape(3)
    d = points - camera_center
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([np.broadcast_to(camera_center, d.shape), d / np.maximum(dist[:, None], 1e-12)], 1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t < dist * (1 - 1e-3) - np.asarray(tolerance, np.float64)
