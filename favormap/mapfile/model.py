"""The in-memory map: what build produces and what mapfile writes (stage boundary)."""

from __future__ import annotations

import dataclasses
import secrets
from dataclasses import dataclass, field

import numpy as np

from ..io import Camera
from .fields import field_name, landmark_datasets


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


def built_for_exact_poses(provenance: dict | None) -> bool:
    """Whether a map of this provenance was built with ``BuildConfig.exact_poses`` (``build --exact-poses``)."""
    return bool((provenance or {}).get("config", {}).get("exact_poses", False))


def map_epipolar_px(provenance: dict | None, which: str = "limit") -> float | None:
    """What the map's build measured of its mapping poses (px at its working resolution): the epipolar
    ``limit`` it tracked with (measured from the matches unless given: how far the poses let a correct match
    lie from its epipolar line) or the right matches' ``median`` distance from their epipolar lines. None
    for maps whose provenance does not record it."""
    key = {"limit": "max_epipolar_px", "median": "epipolar_median_px"}[which]
    v = ((provenance or {}).get("stats") or {}).get(key)
    return float(v) if isinstance(v, (int, float)) and v > 0 else None


def map_aligns_by_default(provenance: dict | None) -> bool:
    """Whether a map of this provenance asks the localizer for the keypoint alignment unless told otherwise
    (``LocalizeConfig.align`` None; its build's ``localize_defaults``: exact poses, or DISK / ALIKED keypoints
    with the observations' pixels stored; maps without the record: no)."""
    return bool((provenance or {}).get("localize_defaults", {}).get("align", False))


def map_estimated_poses(provenance: dict | None) -> dict | None:
    """How the map's poses were estimated from its images (:meth:`favormap.io.sfm.SfmResult.to_dict`: mapper,
    frames registered, ``units`` "arbitrary", "scaled" by ``scale``, or "anchors": moved into the frame of
    known poses of some images, ``anchors`` the fit), or None: poses given with the images,
    in their units."""
    poses = (provenance or {}).get("poses")
    return dict(poses) if isinstance(poses, dict) and poses.get("source") == "sfm" else None


def median_landmark_reproj_error(reproj_error, track_length=None) -> float | None:
    """The map's reprojection-error figure, one definition for build's summary and ``info``: the
    median over landmarks of each landmark's mean reprojection error over its observations (px), over
    the landmarks of three or more observations where ``track_length`` is given and there are any. A
    two-view landmark fits its two rays up to their epipolar residual alone, so its figure says little
    of how well the tracks fit the poses, and maps hold many of them."""
    e = np.asarray(reproj_error)
    if track_length is not None and (np.asarray(track_length) >= 3).any():
        e = e[np.asarray(track_length) >= 3]
    return float(np.median(e)) if e.size else None


class MapCounts:
    """The sizes of a map, in memory (:class:`MapData`) or on disk (:class:`~favormap.mapfile.Map`)."""

    @property
    def num_landmarks(self) -> int:
        return len(self.ids)

    @property
    def num_frames(self) -> int:
        return len(self.frame_names)


@dataclass
class MapData(MapCounts):
    """A whole map in memory. The per-landmark arrays are the schema's (see :mod:`.fields`): those
    named below, and in ``extra`` any the schema adds without a field here (read as attributes)."""

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
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # schema landmark arrays without a field above
    # (O,P,P) uint8 or None: each observation's grey pixels around its keypoint (optional dataset
    # tracks/patch, BuildConfig.align_patches), for the keypoint alignment without the mapping images
    track_patch: np.ndarray | None = None
    # (4, 4) or None: the camera's pose in the frame of the poses the map was built from (optional dataset
    # frames/cam_from_rig; a rotation the build estimated, BuildConfig.camera_rotation): cam_from_world holds
    # the camera's poses, cam_from_rig @ rig_from_world, and the localizer takes and reports rig_from_world
    cam_from_rig: np.ndarray | None = None

    def __getattr__(self, name: str):
        extra = self.__dict__.get("extra") or {}
        if name in extra:
            return extra[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @staticmethod
    def split_landmark_arrays(arrays: dict[str, np.ndarray]) -> tuple[dict, dict]:
        """Per-landmark arrays by name -> (keyword arguments of MapData's own fields, ``extra``)."""
        own = set(MapData.__dataclass_fields__)
        return {k: v for k, v in arrays.items() if k in own}, {k: v for k, v in arrays.items() if k not in own}

    @staticmethod
    def landmark_names() -> tuple[str, ...]:
        """Names of the per-landmark arrays (from the schema)."""
        return tuple(field_name(p) for p in landmark_datasets())

    def select_landmarks(self, idx: np.ndarray) -> MapData:
        """A new map with the landmarks ``idx`` (order kept) and their observations."""
        idx = np.asarray(idx, np.int64)
        remap = np.full(self.num_landmarks, -1, np.int64)
        remap[idx] = np.arange(len(idx))
        keep = remap[self.track_landmark] >= 0
        kw, extra = self.split_landmark_arrays({k: getattr(self, k)[idx] for k in self.landmark_names()})
        return dataclasses.replace(
            self,
            cameras=dict(self.cameras),
            frame_names=list(self.frame_names),
            provenance=dict(self.provenance),
            track_landmark=remap[self.track_landmark[keep]].astype(np.int32),
            track_frame=self.track_frame[keep],
            track_xy=self.track_xy[keep],
            track_patch=None if self.track_patch is None else self.track_patch[keep],
            extra=extra,
            **kw,
        )
