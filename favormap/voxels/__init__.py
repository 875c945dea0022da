"""voxels: per-landmark descriptor + density grids, trained and rendered in batch.

The torch modules (``render``, ``train``) are imported lazily (PEP 562 ``__getattr__``), so that
``favormap.voxels.render_numpy`` -- the localizer's torch-free renderer -- and ``favormap.voxels.config``
can be imported without paying for torch.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .render_numpy import render_from_camera_numpy

if TYPE_CHECKING:
    from .config import QUALITY_PRESETS, TrainingRays, VoxelConfig, VoxelGrids
    from .render import render_from_camera
    from .train import render_training_rays, train_voxels

_LAZY = {
    "render_from_camera": ".render",
    "QUALITY_PRESETS": ".config",
    "TrainingRays": ".config",
    "VoxelConfig": ".config",
    "VoxelGrids": ".config",
    "render_training_rays": ".train",
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


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
