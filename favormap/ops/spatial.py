"""Spatial index over landmark positions (Open3D KD-tree), shared by localize, query, merge and
prune: radius, k-NN and frustum queries, plus an optional occlusion test by raycasting a mesh."""

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


class SpatialIndex:
    """Open3D KD-tree over (L, 3) positions."""

    def __init__(self, positions: np.ndarray):
        self.positions = np.ascontiguousarray(positions, dtype=np.float64)
        self._tree = None
        if len(self.positions):
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.positions))
            self._tree = o3d.geometry.KDTreeFlann(pcd)

    def __len__(self) -> int:
        return len(self.positions)

    def radius(self, center, r: float) -> np.ndarray:
        """Rows within distance ``r`` of ``center`` (sorted)."""
        if self._tree is None:
            return np.zeros(0, np.int64)
        _, idx, _ = self._tree.search_radius_vector_3d(np.asarray(center, np.float64), float(r))
        return np.sort(np.asarray(idx, np.int64))

    def knn(self, center, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows and distances of the ``k`` nearest landmarks (nearest first)."""
        if self._tree is None or k <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        n, idx, d2 = self._tree.search_knn_vector_3d(np.asarray(center, np.float64), int(min(k, len(self))))
        return np.asarray(idx, np.int64), np.sqrt(np.asarray(d2))

    def frustum(self, camera: Camera, cam_from_world: np.ndarray, max_depth: float, min_depth: float = 0.0) -> np.ndarray:
        """Rows of landmarks inside the pinhole camera's frustum between ``min_depth`` and
        ``max_depth``: a KD-tree radius query around the frustum's bounding sphere, then an exact
        projection test on the candidates."""
        if self._tree is None:
            return np.zeros(0, np.int64)
        K = camera.K
        corners_px = np.array([[0, 0], [camera.width, 0], [0, camera.height], [camera.width, camera.height]], float)
        rays = np.c_[(corners_px - K[:2, 2]) / [K[0, 0], K[1, 1]], np.ones(4)]
        wfc_R = cam_from_world[:3, :3].T
        c = camera_centers(cam_from_world)
        far = (rays * max_depth) @ wfc_R.T + c
        near = (rays * min_depth) @ wfc_R.T + c
        pts = np.vstack([far, near, c[None]])
        center = pts.mean(0)
        r = np.linalg.norm(pts - center, axis=1).max()
        cand = self.radius(center, r)
        return cand[project_inside(self.positions[cand], camera, cam_from_world, min_depth, max_depth)]


def project_inside(points: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_depth=0.0, max_depth=np.inf, margin_px=0.0) -> np.ndarray:
    """Mask of points in front of a pinhole camera, inside its image and depth range."""
    Xc = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = Xc[:, 2]
    ok = (z > max(min_depth, 1e-9)) & (z <= max_depth)
    zs = np.where(ok, z, 1.0)
    K = camera.K
    u = K[0, 0] * Xc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / zs + K[1, 2]
    return ok & (u >= margin_px) & (u <= camera.width - margin_px) & (v >= margin_px) & (v <= camera.height - margin_px)


def visible_rows(index: SpatialIndex, camera: Camera, cam_from_world: np.ndarray, view_dir: np.ndarray,
                 view_angle: np.ndarray, depth_range: np.ndarray, limits: ViewLimits = ViewLimits()) -> np.ndarray:
    """Landmarks visible from a pose: in the frustum, within the distance range and the viewing
    angle range they were trained for (paper sec. 3.3). Returns sorted rows."""
    if len(index) == 0:
        return np.zeros(0, np.int64)
    max_depth = float(depth_range[:, 1].max()) * limits.depth_scale[1]
    rows = index.frustum(camera, cam_from_world, max_depth)
    if limits.image_margin_px > 0:
        rows = rows[project_inside(index.positions[rows], camera, cam_from_world, margin_px=limits.image_margin_px)]
    c = camera_centers(cam_from_world)
    v = c - index.positions[rows]
    dist = np.linalg.norm(v, axis=1)
    cosang = np.sum(v * view_dir[rows], 1) / np.maximum(dist, 1e-12)
    ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    ok = (ang <= view_angle[rows] + limits.angle_margin_deg)
    ok &= (dist >= depth_range[rows, 0] * limits.depth_scale[0]) & (dist <= depth_range[rows, 1] * limits.depth_scale[1])
    return rows[ok]


def occluded(points: np.ndarray, camera_center: np.ndarray, mesh, tolerance: float = 1e-3) -> np.ndarray:
    """Mask of points hidden from ``camera_center`` by ``mesh`` (a trimesh.Trimesh or Open3D
    TriangleMesh), by casting a ray to every point with Open3D's RaycastingScene."""
    if not isinstance(mesh, o3d.t.geometry.TriangleMesh):
        if isinstance(mesh, o3d.geometry.TriangleMesh):
            mesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
        else:  # trimesh
            tm = o3d.t.geometry.TriangleMesh()
            tm.vertex.positions = o3d.core.Tensor(np.asarray(mesh.vertices, np.float32))
            tm.triangle.indices = o3d.core.Tensor(np.asarray(mesh.faces, np.int32))
            mesh = tm
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    d = points - camera_center
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([np.broadcast_to(camera_center, d.shape), d / np.maximum(dist[:, None], 1e-12)], 1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t < dist * (1 - tolerance) - tolerance
