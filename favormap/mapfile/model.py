"""The in-memory map: what build produces and what mapfile writes (stage boundary)."""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field

import numpy as np

from ..io import Camera


def new_landmark_ids(n: int, avoid: np.ndarray | None = None) -> np.ndarray:
    """``n`` unique random 64-bit ids (stable across prune/merge; unlikely to collide across maps)."""
    rng = np.random.default_rng(secrets.randbits(64))
    taken = set() if avoid is None else set(np.asarray(avoid, np.uint64).tolist())
    ids = np.empty(0, np.uint64)
    while len(ids) < n:
        cand = rng.integers(1, np.iinfo(np.int64).max, size=n - len(ids), dtype=np.int64).astype(np.uint64)
        cand = np.unique(cand)
        cand = cand[~np.isin(cand, ids)]
        if taken:
            cand = cand[~np.isin(cand, np.fromiter(taken, np.uint64))]
        ids = np.concatenate([ids, cand])
    return ids[:n]


def median_landmark_reproj_error(reproj_error) -> float | None:
    """The map's reprojection-error figure, one definition for build's summary and ``info``: the
    median over landmarks of each landmark's mean reprojection error over its observations (px)."""
    e = np.asarray(reproj_error)
    return float(np.median(e)) if e.size else None


@dataclass
class MapData:
    extractor: str
    channels: int
    grid_resolution: int
    patch_size: int
    render_samples: int
    max_side: int
    # landmarks (L)
    ids: np.ndarray  # uint64
    positions: np.ndarray  # (L,3) float64, world
    voxel_size: np.ndarray  # (L,) float32, world units
    track_length: np.ndarray  # (L,) int32
    reproj_error: np.ndarray  # (L,) float32, mean px
    quality: np.ndarray  # (L,) float32, training PSNR dB (MAX=2)
    cosine: np.ndarray  # (L,) float32
    view_dir: np.ndarray  # (L,3) float32 unit, landmark -> training cameras (mean)
    view_angle: np.ndarray  # (L,) float32 deg, largest angle of a training view from view_dir
    depth_range: np.ndarray  # (L,2) float32, min/max distance of training views
    mean_descriptor: np.ndarray  # (L,C) float32
    descriptors: np.ndarray  # (L,R,R,R,C) float32
    density: np.ndarray  # (L,R,R,R) float32 raw density
    # cameras and frames
    cameras: dict[int, Camera]
    frame_names: list[str]
    frame_camera_ids: np.ndarray  # (M,) int32
    cam_from_world: np.ndarray  # (M,4,4)
    # observations (O)
    track_landmark: np.ndarray  # (O,) int32 row into the landmark arrays
    track_frame: np.ndarray  # (O,) int32 row into the frame arrays
    track_xy: np.ndarray  # (O,2) float32 keypoint pixels (working resolution)
    provenance: dict = field(default_factory=dict)

    @property
    def num_landmarks(self) -> int:
        return len(self.ids)

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)

    LANDMARK_FIELDS = ("ids", "positions", "voxel_size", "track_length", "reproj_error", "quality", "cosine",
                       "view_dir", "view_angle", "depth_range", "mean_descriptor", "descriptors", "density")

    def select_landmarks(self, idx: np.ndarray) -> "MapData":
        """A new map with the landmarks ``idx`` (order kept) and their observations."""
        idx = np.asarray(idx, np.int64)
        remap = np.full(self.num_landmarks, -1, np.int64)
        remap[idx] = np.arange(len(idx))
        keep = remap[self.track_landmark] >= 0
        kw = {k: getattr(self, k)[idx] for k in self.LANDMARK_FIELDS}
        return MapData(
            extractor=self.extractor, channels=self.channels, grid_resolution=self.grid_resolution,
            patch_size=self.patch_size, render_samples=self.render_samples, max_side=self.max_side,
            cameras=dict(self.cameras), frame_names=list(self.frame_names), frame_camera_ids=self.frame_camera_ids,
            cam_from_world=self.cam_from_world, track_landmark=remap[self.track_landmark[keep]].astype(np.int32),
            track_frame=self.track_frame[keep], track_xy=self.track_xy[keep], provenance=dict(self.provenance), **kw)
