"""Map-operation side of the spatial queries: the visibility index and tests live in
:mod:`favormap.visibility` (re-exported here); this module adds the Open3D occlusion test
(raycasting a mesh)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..visibility import (  # noqa: F401  (re-exported for the map operations)
    KD_BACKENDS,
    SpatialIndex,
    ViewLimits,
    frustum_sphere,
    morton_order,
    project_inside,
    reach_sphere,
    visible_mask,
    visible_rows,
)


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
    rays = np.concatenate([np.broadcast_to(camera_center, d.shape), d / np.maximum(dist[:, None], 1e-12)], 1).astype(
        np.float32
    )
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t < dist * (1 - 1e-3) - np.asarray(tolerance, np.float64)
