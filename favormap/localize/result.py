"""What the localizer returns (:class:`LocalizationResult`, one :class:`IterationResult` per step) and
the query state its stages share (:class:`Query`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io import Camera
from .covariance import PoseCovariance


@dataclass
class IterationResult:
    cam_from_world: np.ndarray
    num_visible: int
    num_matches: int
    num_inliers: int
    success: bool  # PnP found a pose with enough inliers (not yet the final checks)
    kind: str = "render"  # "render" (from the previous estimate) or "global" (no prior)


@dataclass
class LocalizationResult:
    success: bool
    cam_from_world: np.ndarray  # final estimate (the prior when not successful)
    num_matches: int
    num_inliers: int
    iterations: list[IterationResult]
    # seconds per stage: extraction (image reading included), visibility, loading, rendering, matching, pnp (with
    # the final refinement). From a prior, the first iteration's visibility, loading and rendering run while the
    # features are extracted, so the stages then add up to more than the query took
    timings: dict[str, float]
    message: str = ""
    checks: dict = field(default_factory=dict)  # measured values of the success checks
    # for visualisation / analysis (last successful iteration)
    keypoints: np.ndarray | None = None
    matches: np.ndarray | None = None  # (K, 2) [landmark row, query keypoint]
    inlier_mask: np.ndarray | None = None
    match_similarity: np.ndarray | None = None  # (K,) cosine of landmark vs query descriptor per match
    estimate: np.ndarray | None = None  # last PnP estimate even when the checks refused it
    # (K,) True for the matches that only the guided step found (by projection, not among the
    # descriptor-matched inliers); None when the pose did not take the guided step
    by_projection: np.ndarray | None = None
    # uncertainty of a successful pose (favormap.localize.refine.PoseCovariance; None when the final
    # weighted refinement is off)
    covariance: PoseCovariance | None = None
    camera: Camera | None = None  # the working pinhole camera of ``keypoints`` (undistorted, resized)
    # (K, 2) with LocalizeConfig.align: each match's keypoint as the final refinement used it, moved to
    # the mapping images (NaN where not an inlier or not aligned); None when alignment is off
    aligned: np.ndarray | None = None
    prior: np.ndarray | None = None  # the cam_from_world prior localization started from (None: without one)
    # the final estimate of the camera the image was taken with, in the frame of the map's landmarks and frames
    # (Map.cam_from_rig @ cam_from_world); cam_from_world itself is in the convention of the poses the map was
    # built from, as the prior is. The same matrix for maps without frames/cam_from_rig
    image_cam_from_world: np.ndarray | None = None

    def to_json(self) -> dict:
        from ..geometry import inverse, rotmat_to_quat

        T = self.cam_from_world
        return {
            "success": bool(self.success),
            "message": self.message,
            "world_from_cam": inverse(T).tolist(),
            "cam_from_world": {"quaternion_xyzw": rotmat_to_quat(T[:3, :3]).tolist(), "translation": T[:3, 3].tolist()},
            "num_matches": int(self.num_matches),
            "num_inliers": int(self.num_inliers),
            "checks": {k: (round(v, 5) if isinstance(v, float) else v) for k, v in self.checks.items()},
            "uncertainty": None if self.covariance is None else self.covariance.to_json(),
            "iterations": [
                {
                    "kind": it.kind,
                    "cam_from_world": it.cam_from_world.tolist(),
                    "num_visible": it.num_visible,
                    "num_matches": it.num_matches,
                    "num_inliers": it.num_inliers,
                    "success": it.success,
                }
                for it in self.iterations
            ],
            "timings": {k: round(v, 5) for k, v in self.timings.items()},
            **({} if self.aligned is None else {"num_aligned": int(np.isfinite(self.aligned[:, 0]).sum())}),
        }


@dataclass
class Query:
    """One query image as the localizer's stages share it (its features, camera, and what they computed)."""

    feats: object
    desc: np.ndarray  # (N, C) float32 unit descriptors
    cam: Camera
    global_pose: tuple | None = None  # (pose or None, IterationResult) of the prior-free step, once computed
    # that step's matches: (landmark positions (K, 3), query keypoint indices (K,)), once computed
    global_matches: tuple | None = None
    image: np.ndarray | None = None  # the working image (LocalizeConfig.align)
    gray: np.ndarray | None = None  # its blurred grey version, once aligned
    aligned: np.ndarray | None = None  # (K, 2) the last final refinement's aligned keypoints by match
    seen: object | None = None  # favormap.localize.descriptors.SeenRays: the descriptors it got, by landmark
