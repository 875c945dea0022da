"""voxels: per-landmark descriptor + density grids, trained and rendered in batch.

The stage modules are imported on first use (PEP 562 ``__getattr__``): ``favormap.voxels.config`` imports
neither numpy nor torch, ``favormap.voxels.render_numpy`` -- the localizer's renderer on the CPU -- no torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..lazy import lazy_exports

if TYPE_CHECKING:
    from .config import QUALITY_PRESETS, TrainingRays, VoxelConfig, VoxelGrids
    from .quality import render_training_rays
    from .render import render_from_camera
    from .render_numpy import render_from_camera_numpy
    from .train import train_voxels

_LAZY = {
    "render_from_camera": ".render",
    "render_from_camera_numpy": ".render_numpy",
    "QUALITY_PRESETS": ".config",
    "TrainingRays": ".config",
    "VoxelConfig": ".config",
    "VoxelGrids": ".config",
    "render_training_rays": ".quality",
    "train_voxels": ".train",
}

__all__ = [
    "QUALITY_PRESETS",
    "TrainingRays",
    "VoxelConfig",
    "VoxelGrids",
    "render_from_camera",
    "render_from_camera_numpy",
    "render_training_rays",
    "train_voxels",
]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
