"""Exporting a map's landmarks for viewing in other tools (trimesh): .ply, .obj, .glb.

- landmarks: a point cloud (one vertex per landmark) coloured by quality (training PSNR) or track
  length (viridis ramp between the 2nd and 98th percentiles);
- ``boxes``: one axis-aligned cube per landmark with its voxel size (8 vertices, 12 triangles),
  coloured like its landmark. A .glb holds two nodes (points and boxes, the boxes half
  transparent); .ply and .obj hold one geometry only, so with ``boxes`` they hold the boxes (whose
  centres are the landmarks).

Only landmark metadata is read (no voxel grids).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..colors import viridis
from ..errors import InputError
from ..mapfile import Map, atomic_path
from ..mapfile.writer import check_output_path

FORMATS = (".ply", ".obj", ".glb")
COLOR_BY = ("quality", "track")

# a unit cube around the origin: 8 corners, 12 outward-facing triangles
_CUBE_V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
_CUBE_F = np.array(
    [
        [0, 1, 3],
        [0, 3, 2],
        [4, 6, 7],
        [4, 7, 5],
        [0, 4, 5],
        [0, 5, 1],
        [2, 3, 7],
        [2, 7, 6],
        [0, 2, 6],
        [0, 6, 4],
        [1, 5, 7],
        [1, 7, 3],
    ],
    np.int64,
)


def colormap(values: np.ndarray, lo: float | None = None, hi: float | None = None) -> tuple[np.ndarray, float, float]:
    """RGBA uint8 colours (viridis) of ``values``; returns (colours, lo, hi) of the ramp."""
    rgb, lo, hi = viridis(values, lo, hi)
    return np.c_[rgb, np.full(len(rgb), 255, np.uint8)], lo, hi


def box_mesh_arrays(positions: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8L, 3) and faces (12L, 3) of one axis-aligned cube per landmark."""
    P = np.asarray(positions, np.float64).reshape(-1, 3)
    s = np.asarray(sizes, np.float64).reshape(-1)
    V = (P[:, None, :] + s[:, None, None] * _CUBE_V[None]).reshape(-1, 3)
    F = (_CUBE_F[None] + 8 * np.arange(len(P))[:, None, None]).reshape(-1, 3)
    return V, F


@dataclass
class ExportResult:
    path: Path
    num_points: int
    num_boxes: int
    color_by: str
    value_range: tuple

    def to_dict(self) -> dict:
        return {
            "output": str(self.path),
            "num_points": self.num_points,
            "num_boxes": self.num_boxes,
            "color_by": self.color_by,
            "value_range": list(self.value_range),
        }


def export_landmarks(m, out, boxes: bool = False, color_by: str = "quality") -> ExportResult:
    """Write the landmarks of ``m`` (a Map, MapData, or a map path) to ``out`` (format from the suffix)."""
    import trimesh

    out = Path(out)
    ext = out.suffix.lower()
    if ext not in FORMATS:
        raise InputError(f"cannot export to {out.name}: the file name must end in {', '.join(FORMATS)}")
    if color_by not in COLOR_BY:
        raise InputError(f"unknown colouring {color_by!r} (use {' or '.join(COLOR_BY)})")
    check_output_path(out, [m] if isinstance(m, (str, Path)) else [getattr(m, "path", None)])
    if isinstance(m, (str, Path)):
        with Map.open(m) as mm:
            return export_landmarks(mm, out, boxes, color_by)
    P = np.asarray(m.positions, np.float64)
    if len(P) == 0:
        raise InputError("the map has no landmarks to export")
    vals = np.asarray(m.quality if color_by == "quality" else m.track_length, np.float64)
    colors, lo, hi = colormap(vals)
    geoms = {}
    if not boxes or ext == ".glb":
        geoms["landmarks"] = trimesh.PointCloud(P, colors=colors)
    if boxes:
        V, F = box_mesh_arrays(P, m.voxel_size)
        c = np.repeat(colors, 8, axis=0)
        if ext == ".glb":
            c[:, 3] = 160
        geoms["voxels"] = trimesh.Trimesh(V, F, vertex_colors=c, process=False)
    obj = next(iter(geoms.values())) if len(geoms) == 1 else trimesh.Scene(geoms)
    with atomic_path(out) as tmp:
        data = obj.export(file_type=ext[1:])
        if isinstance(data, str):
            data = data.encode()
        Path(tmp).write_bytes(data)
    return ExportResult(out, len(P) if "landmarks" in geoms else 0, len(P) if boxes else 0, color_by, (lo, hi))
