"""The settings of a build (:class:`BuildConfig`) and the defaults it takes from the extractor's policy.
Neither numpy nor torch is imported with it: the CLI reads the defaults from here."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .voxels.config import VoxelConfig


def _policy(extractor: str):
    from .features import policy_of  # numpy: imported on use, so that the CLI reads the defaults cheaply

    return policy_of(extractor)


def default_max_epipolar(extractor: str) -> float:
    """The least epipolar limit of tracking for ``extractor`` (its policy's keypoint precision, px)."""
    return _policy(extractor).keypoint_precision_px


def default_align_patches(extractor: str) -> int:
    """The stored observation patches' radius a build of ``extractor`` uses when none is given (0: none)."""
    return _policy(extractor).align_patches


# BuildConfig.exact_poses: the track alignment's window (px) and the stored observation patches' radius
EXACT_POSES_REFINE_WINDOW = 9
EXACT_POSES_PATCHES = 20
# a mapping frame keeps at least this share of the landmark budget where its tracks allow
# (BuildConfig.min_frame_landmarks): 300 of 3,000
MIN_FRAME_SHARE = 0.1


def localize_defaults(config: BuildConfig) -> dict:
    """What a map built with ``config`` asks of the localizer unless told otherwise (stored in the map's
    provenance as ``localize_defaults``; LocalizeConfig fields left None follow it): the keypoint alignment
    where the poses are exact or the extractor's policy asks for it, with the stored patches it needs."""
    aligning = _policy(config.extractor).align_patches > 0
    align = config.exact_poses or (aligning and config.align_patches > 0)
    return {"align": bool(align)}


@dataclass
class BuildConfig:
    """Settings of :func:`build_map`. Fields left None follow the extractor's policy
    (:class:`favormap.features.ExtractorPolicy`) or are measured from the data; the reasons for the
    defaults are in docs/implementation-notes.md."""

    extractor: str = "sift"  # a registered feature extractor (favormap.features.available())
    max_keypoints: int = 2048  # keypoints per mapping image
    max_side: int = 640  # images are downscaled so that max(w, h) <= max_side (0: keep)
    # frames a track must span to become a landmark: two-view tracks fill the landmark budget that longer
    # tracks leave (select_landmarks keeps the longest first)
    min_track: int = 2
    # each frame is matched with this many next frames (as listed, or along a path through the poses where the
    # listing is none: favormap.frame_order)
    match_window: int = 10
    # tracking's epipolar limit (px at the working resolution). None: measured from the mutual matches
    # (favormap.tracking.epipolar_limit: 3x the right matches' median distance from their epipolar lines),
    # no less than the extractor's keypoint precision (ExtractorPolicy.keypoint_precision_px)
    max_epipolar_px: float | None = None
    min_similarity: float = 0.7  # cosine similarity of a tracking match
    # align each landmark's observations to its middle one through its local plane, then triangulate again
    # (triangulation.refine_observations: Lucas-Kanade in a window of this many pixels; 0: off)
    refine_window: int = 0
    # store each observation's (2r+1)^2 grey pixels in the map (optional dataset tracks/patch; 0: none), so
    # that localize --align needs no mapping images (favormap.localize.align). None: ExtractorPolicy.align_patches
    align_patches: int | None = None
    # the mapping poses are exact (a simulator, motion capture; not SLAM or SfM): the tracks are aligned as
    # refine_window does (EXACT_POSES_REFINE_WINDOW unless refine_window is given), each observation's pixels
    # are stored (EXACT_POSES_PATCHES unless align_patches is given), and localization aligns each inlier's
    # keypoint to them unless told otherwise (LocalizeConfig.align None: the map's choice)
    exact_poses: bool = False
    # refine the mapping poses with the landmarks by bundle adjustment, each camera centre held near its given
    # position (favormap.pose_refinement), then triangulate again; the map stores the refined poses. For poses
    # that fit the images less well than the extractor places keypoints (the build says so: the right tracking
    # matches' median epipolar distance above ExtractorPolicy.keypoint_precision_px), such as motion capture's
    refine_poses: bool = False
    # estimate the one rotation by which the images' camera is turned against the given poses (a hand-eye
    # calibration's error, shared by every frame; favormap.pose_refinement.estimate_camera_rotation) and
    # triangulate with the camera's poses; the map stores it (frames/cam_from_rig) and the localizer takes and
    # reports poses in the given poses' frame. None: where the poses fit the images less well than the
    # extractor places keypoints (the rule under which the build suggests refine_poses), which refine_poses
    # already covers
    camera_rotation: bool | None = None
    max_reproj_px: float = 5.0  # a landmark's largest reprojection error in its observations
    min_angle_deg: float = 1.0  # a landmark's least triangulation angle
    max_landmarks: int = 3000  # the longest tracks are kept
    # then every mapping frame that sees fewer landmarks than this gets its best remaining tracks up to
    # this count (build.landmark_budget), so that queries near weakly covered frames find enough of them.
    # None: a tenth of max_landmarks (MIN_FRAME_SHARE); 0: the budget alone
    min_frame_landmarks: int | None = None
    # landmarks trained together in one task (seeded voxel.seed + batch index): the map depends on
    # this, not on who runs the batches (LocalExecutor or Ray workers)
    train_batch: int = 1024
    voxel: VoxelConfig | None = None  # None: the preset ExtractorPolicy.training_quality names
    # CPU threads for torch/OpenCV: None leaves the process's pools (and heap policy) alone; "auto" applies
    # favormap.threads' rule, a number fixes them (favormap.threads.thread_count); not stored in the map
    threads: int | str | None = None

    def __post_init__(self):
        if self.min_frame_landmarks is None:
            self.min_frame_landmarks = int(self.max_landmarks * MIN_FRAME_SHARE)
        if self.voxel is None:
            self.voxel = VoxelConfig.preset(_policy(self.extractor).training_quality)
        if self.align_patches is None:
            self.align_patches = default_align_patches(self.extractor)
        if self.exact_poses:
            self.refine_window = self.refine_window or EXACT_POSES_REFINE_WINDOW
            self.align_patches = self.align_patches or EXACT_POSES_PATCHES

    def triangulation(self):
        """This build's triangulation settings (:class:`favormap.triangulation.TriangulationConfig`), for
        the build and for an extension of its map."""
        from .triangulation import TriangulationConfig

        return TriangulationConfig(self.max_reproj_px, self.min_angle_deg, min_track=self.min_track)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("threads")
        return d
