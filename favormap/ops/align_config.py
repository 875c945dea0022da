"""Settings of map alignment (:func:`favormap.ops.align.align_maps`): a plain dataclass, importable without
numpy (the CLI reads its defaults from here)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class AlignConfig:
    """How two maps' landmarks are matched and when their alignment is refused."""

    ratio: float = 0.9  # descriptor distance ratio (nearest / second nearest) below which a match is kept
    threshold: float | None = None  # inlier distance in a's units (None: 2x a's median voxel size)
    iterations: int = 4000  # RANSAC hypotheses
    min_matches: int = 12  # refuse below this many descriptor matches
    min_inliers: int = 12  # refuse below this many agreeing landmarks
    min_inlier_ratio: float = 0.15  # refuse when fewer than this share of the matches agree
    min_spread: float = 0.05  # inliers' 2nd / 1st principal std in a; below: collinear (degenerate)
    guided_radius: tuple = (3.0, 1.0)  # rounds of guided matching and refinement, radius in thresholds
    jackknife_blocks: int = 8  # blocks of consecutive frames per map behind the uncertainty
    seed: int = 0
