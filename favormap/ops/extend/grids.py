"""The map's voxel grids as the extension reads them: a landmark's grids as float32 arrays, and the
descriptors they render towards a camera."""

from __future__ import annotations

import numpy as np


def unit(x) -> np.ndarray:
    """The rows of ``x`` scaled to unit length (float32)."""
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def grids_of(m, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxel grids of the map ``m``'s landmarks ``rows``: descriptors (n, R^3, C) and density (n, R^3), float32."""
    R3 = m.grid_resolution**3
    desc = np.asarray(m.descriptors[rows], np.float32).reshape(len(rows), R3, -1)
    return desc, np.asarray(m.density[rows], np.float32).reshape(len(rows), R3)


def render_towards(m, rows: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
    """(n, C) descriptors the grids of the map ``m``'s landmarks ``rows`` render towards the camera
    ``cam_from_world`` (:func:`favormap.voxels.render_numpy.render_from_camera_numpy`)."""
    from ...geometry import camera_centers
    from ...voxels.render_numpy import render_from_camera_numpy

    return render_from_camera_numpy(
        *grids_of(m, rows),
        np.asarray(m.positions[rows], np.float32),
        np.asarray(m.voxel_size[rows], np.float32),
        np.asarray(camera_centers(cam_from_world), np.float32),
        m.render_samples,
    )
