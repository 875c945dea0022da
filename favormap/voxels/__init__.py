"""voxels: per-landmark descriptor + density grids, trained and rendered in batch."""

from .render import render_from_camera
from .train import QUALITY_PRESETS, TrainingRays, VoxelConfig, VoxelGrids, render_training_rays, train_voxels

__all__ = [
    "QUALITY_PRESETS",
    "TrainingRays",
    "VoxelConfig",
    "VoxelGrids",
    "render_from_camera",
    "render_training_rays",
    "train_voxels",
]
