"""The build's last stage: the trained landmarks, their statistics and provenance as one :class:`MapData`.

The types at the boundary of the build's landmark stage (:class:`TrackSummary`, :class:`BuildLandmarks`)
and what the map stores of each landmark beyond its grids (view geometry, mean descriptor, the observations'
pixels) live here, so that :mod:`favormap.build` reads as its sequence of stages.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .build_config import BuildConfig, localize_defaults
from .extraction import FrameFeatures
from .features import patch_offsets
from .geometry import camera_centers, sum_by_group, view_geometry
from .io import Sequence
from .io.images import decode_and_prepare, patches_around
from .mapfile.model import MapData, median_landmark_reproj_error, new_landmark_ids
from .pose_refinement import CameraRotation, PoseRefinement
from .tracking import Tracks
from .triangulation import Landmarks
from .voxels import TrainingRays
from .voxels.config import VoxelGrids


@dataclass(frozen=True)
class TrackSummary:
    """What the map's statistics keep of all the tracks once only the selected landmarks' go on."""

    tracks: int
    triangulated: int  # tracks that triangulated, before the landmark budget
    epipolar_kept: float  # share of the mutual matches within the epipolar limit (favormap.tracking.Tracks)
    epipolar_kept_3x: float  # ... within 3x the limit
    max_epipolar_px: float  # the limit used: given, or measured
    epipolar_median_px: float  # the right matches' median distance from their epipolar lines (NaN: not measured)

    @classmethod
    def of(cls, tracks: Tracks, triangulated: int) -> TrackSummary:
        return cls(
            tracks=len(tracks),
            triangulated=triangulated,
            epipolar_kept=tracks.epipolar_matches / max(tracks.matches, 1),
            epipolar_kept_3x=tracks.epipolar_matches_3x / max(tracks.matches, 1),
            max_epipolar_px=tracks.max_epipolar_px,
            epipolar_median_px=tracks.epipolar_median_px,
        )


@dataclass
class BuildLandmarks:
    """The landmark stage's result: the selected landmarks, the frames with the poses they were
    triangulated with (refined where the build refines them) and the summary of the tracks."""

    lms: Landmarks
    ff: FrameFeatures
    refinement: PoseRefinement | None
    summary: TrackSummary
    rotation: CameraRotation | None = None  # the camera's rotation against the given poses, where estimated

    @property
    def cam_from_rig(self) -> np.ndarray | None:
        """The camera's pose in the frame of the given poses (None: the given poses are the camera's)."""
        if self.rotation is not None:
            return self.rotation.cam_from_rig if self.rotation.holds else None
        return None if self.refinement is None else self.refinement.cam_from_rig


@dataclass
class BuildRun:
    """How the build ran, as the map's provenance records it."""

    timings: dict[str, float]  # seconds per stage
    executor: str  # Executor.describe()
    feature_cache: str  # "memory" or the cache file's path


def landmark_geometry(lms: Landmarks, cam_from_world: np.ndarray):
    """Viewing direction (unit, landmark -> cameras), angular radius (deg) and depth range of the
    training views of each landmark."""
    return view_geometry(lms.positions, lms.tracks.track_of_obs, camera_centers(cam_from_world)[lms.tracks.frame_idx])


def track_mean_descriptors(
    rays: TrainingRays, n_landmarks: int, patch_size: int, mean_patch: int = 0, patch_stride: int = 1
) -> np.ndarray:
    """(L, C) unit mean descriptor of each landmark: the mean over its observations of the central
    ``mean_patch`` x ``mean_patch`` pixels of each training patch (0, or at least ``patch_size``: the
    whole patch), as ``landmarks/mean_descriptor`` stores it."""
    if mean_patch < 0:
        raise ValueError(f"VoxelConfig.mean_patch must be >= 0 (0: the whole patch), not {mean_patch}")
    half = (mean_patch or patch_size) / 2
    central = np.flatnonzero(np.abs(patch_offsets(patch_size, patch_stride)).max(1) < half)
    means = (
        rays.patch_means()
        if len(central) == rays.targets.shape[1]
        else rays.targets[:, central].mean(1, dtype=np.float32)
    )
    out = sum_by_group(means, rays.obs_landmark, n_landmarks)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def frame_gray(seq: Sequence, ff: FrameFeatures, f: int, config: BuildConfig) -> np.ndarray:
    """Frame ``f``'s grey working image (uint8): the one SIFT's sampling state holds, or the frame
    decoded again for the extractors whose features hold none."""
    import cv2

    gray = getattr(ff.features[f].dense, "gray", None)
    if gray is None:
        fr = seq.frames[f]
        img = decode_and_prepare(None, fr.image_path, seq.cameras[fr.camera_id], config.max_side)[0]
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return gray


def observation_patches(lms: Landmarks, seq: Sequence, ff: FrameFeatures, config: BuildConfig) -> np.ndarray:
    """The (O, P, P) grey pixels around every observation of ``lms`` (``config.align_patches``), frame by frame."""
    r = int(config.align_patches)
    tr = lms.tracks
    out = np.empty((len(tr.xy), 2 * r + 1, 2 * r + 1), np.uint8)
    for f in np.unique(tr.frame_idx):
        sel = np.flatnonzero(tr.frame_idx == f)
        out[sel] = patches_around(frame_gray(seq, ff, int(f), config), tr.xy[sel], r)
    return out


def build_stats(seq: Sequence, config: BuildConfig, found: BuildLandmarks, grids: VoxelGrids) -> dict:
    """The build's statistics (``provenance/stats``) from its stages' results."""
    lms, s, ff = found.lms, found.summary, found.ff
    return {
        "frames": len(seq.frames),
        "frames_extracted": len(seq.frames) if ff.extracted is None else ff.extracted,
        "tracks": int(s.tracks),
        # shares of the mutual matches within the epipolar limit and 3x it (favormap.tracking.Tracks)
        "epipolar_kept": round(s.epipolar_kept, 4),
        "epipolar_kept_3x": round(s.epipolar_kept_3x, 4),  # within 3x the limit
        "max_epipolar_px": float(s.max_epipolar_px),  # the limit used: given, or measured
        "epipolar_measured": config.max_epipolar_px is None,
        # the right matches' median distance from their epipolar lines (px; measured limits only)
        **(
            {"epipolar_median_px": round(s.epipolar_median_px, 3)}
            if s.epipolar_median_px == s.epipolar_median_px
            else {}
        ),
        "triangulated": int(s.triangulated),
        "landmarks": int(len(lms)),
        "max_landmarks": int(config.max_landmarks),  # the budget
        "min_frame_landmarks": int(config.min_frame_landmarks),  # and the least a mapping frame keeps
        # landmarks beyond the budget, kept for frames that would see fewer than min_frame_landmarks
        "coverage_landmarks": max(int(len(lms)) - int(config.max_landmarks), 0),
        "two_view_landmarks": int((lms.tracks.lengths == 2).sum()),  # tracks of two frames among the landmarks
        "mean_track_length": float(lms.tracks.lengths.mean()),
        # one definition with `favormap info` (Map.info): the median over landmarks of each landmark's mean
        # reprojection error over its observations, as stored (float32) in landmarks/reproj_error
        "median_reproj_error_px": median_landmark_reproj_error(
            lms.mean_reproj_error.astype(np.float32), lms.tracks.lengths
        ),
        **({"poses_refined": False} if found.refinement is None else found.refinement.stats()),
        **({} if found.rotation is None else found.rotation.stats()),
        "median_psnr": float(np.median(grids.psnr)),
        "median_cosine": float(np.median(grids.cosine)),
    }


def build_map_data(
    seq: Sequence,
    config: BuildConfig,
    found: BuildLandmarks,
    rays: TrainingRays,
    grids: VoxelGrids,
    run: BuildRun,
) -> MapData:
    """The map of the trained landmarks (with their observations' pixels where ``config.align_patches``
    asks for them); its provenance: ``run``, the source, the configuration and the statistics."""
    lms, ff, vox = found.lms, found.ff, config.voxel
    view_dir, view_angle, depth_range = landmark_geometry(lms, ff.cam_from_world)
    mean_desc = track_mean_descriptors(rays, len(lms), vox.patch_size, vox.mean_patch, vox.patch_stride)
    stats = build_stats(seq, config, found, grids)
    R = vox.resolution
    return MapData(
        extractor=config.extractor,
        channels=rays.targets.shape[-1],
        grid_resolution=R,
        patch_size=vox.patch_size,
        render_samples=vox.samples,
        max_side=config.max_side,
        ids=new_landmark_ids(len(lms)),
        positions=lms.positions,
        voxel_size=rays.sizes.astype(np.float32),
        track_length=lms.tracks.lengths.astype(np.int32),
        reproj_error=lms.mean_reproj_error.astype(np.float32),
        quality=grids.psnr,
        cosine=grids.cosine,
        view_dir=view_dir.astype(np.float32),
        view_angle=view_angle.astype(np.float32),
        depth_range=depth_range.astype(np.float32),
        mean_descriptor=mean_desc.astype(np.float32),
        descriptors=grids.descriptors.cpu().numpy().reshape(len(lms), R, R, R, -1),
        density=grids.density.cpu().numpy().reshape(len(lms), R, R, R),
        cameras=dict(seq.cameras),
        frame_names=[f.name for f in seq.frames],
        frame_camera_ids=np.array([f.camera_id for f in seq.frames], np.int32),
        cam_from_world=ff.cam_from_world,
        cam_from_rig=found.cam_from_rig,
        track_landmark=lms.tracks.track_of_obs.astype(np.int32),
        track_frame=lms.tracks.frame_idx.astype(np.int32),
        track_xy=lms.tracks.xy.astype(np.float32),
        track_patch=observation_patches(lms, seq, ff, config) if config.align_patches else None,
        provenance={
            "source": str(seq.root),
            "source_format": seq.format,
            "config": config.to_dict(),
            "localize_defaults": localize_defaults(config),
            "timings": run.timings,
            "stats": stats,
            "training_history": grids.history,
            "executor": run.executor,
            "feature_cache": run.feature_cache,
        },
    )
