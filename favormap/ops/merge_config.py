"""Settings of map merging (:func:`favormap.ops.merge.merge_maps`): a plain dataclass, importable without
numpy (the CLI reads its defaults from here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class MergeConfig:
    """Which landmarks of later maps are duplicates of landmarks already in the merged map."""

    dedup: bool = True  # False: keep every landmark
    # a later landmark closer than this to an existing one can be its duplicate (None: the existing landmark's
    # voxel size), in the first map's units
    dedup_radius: float | None = None
    min_cosine: float = 0.8  # ... when their mean descriptors' cosine similarity is above this
