"""build: posed image sequence -> trained feature-voxel map (in memory; mapfile writes it).

Stages: extract (:mod:`favormap.extraction`) -> track -> triangulate -> select -> patches
(:mod:`favormap.voxels.rays`) -> train (:mod:`favormap.voxels.batches`). Each stage hands one dataclass to
the next; ``build_map`` runs them and records timings and statistics.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import features as feats_mod
from .build_config import (
    EXACT_POSES_PATCHES,
    EXACT_POSES_REFINE_WINDOW,
    BuildConfig,
    default_align_patches,
    default_max_epipolar,
    localize_defaults,
)
from .errors import FavormapError, InputError, SequenceError
from .executor import Executor, LocalExecutor
from .extraction import (
    MAP_CHUNK,
    ExtractorSpec,
    ExtractTask,
    FrameFeatures,
    extract_frame,
    extract_sequence,
    map_into,
)
from .features import patch_offsets
from .features.base import check_patch
from .features.cache import FeatureCache
from .geometry import camera_centers, sum_by_group, view_geometry
from .heap import release_free_memory, reuse_freed_blocks
from .io import Sequence
from .io.images import decode_and_prepare, patches_around
from .mapfile.model import MapData, median_landmark_reproj_error, new_landmark_ids
from .pose_refinement import refine_poses
from .threads import rebalance, thread_count
from .tracking import Tracks, track_features
from .triangulation import Landmarks, TriangulationConfig, refine_observations, triangulate
from .voxels import TrainingRays
from .voxels.batches import TrainTask, batch_bounds, rays_subset, train_batch, train_batches
from .voxels.config import voxel_config_for
from .voxels.rays import PatchLayout, PatchTask, patch_targets, sample_patches, training_rays

# the build's stages, importable from here whichever module holds them
__all__ = [
    "BuildConfig",
    "BuildObserver",
    "EXACT_POSES_PATCHES",
    "EXACT_POSES_REFINE_WINDOW",
    "ExtractTask",
    "ExtractorSpec",
    "FrameFeatures",
    "MAP_CHUNK",
    "MEMORY_FRAMES",
    "PatchLayout",
    "PatchTask",
    "TrainTask",
    "batch_bounds",
    "build_map",
    "check_build_input",
    "default_align_patches",
    "default_max_epipolar",
    "extract_frame",
    "extract_sequence",
    "frame_gray",
    "landmark_geometry",
    "localize_defaults",
    "map_into",
    "observation_patches",
    "patch_targets",
    "rays_subset",
    "refine_landmarks",
    "sample_patches",
    "select_landmarks",
    "track_frames",
    "track_mean_descriptors",
    "train_batch",
    "train_batches",
    "training_rays",
    "triangulate_tracks",
]


class BuildObserver:
    """Hooks called at the stage boundaries of :func:`build_map` (e.g. the rerun recorder).
    Every method is optional; the default does nothing."""

    def on_frames(self, seq: Sequence, ff: FrameFeatures, images: list | None) -> None: ...
    def on_tracks(self, tracks: Tracks, ff: FrameFeatures) -> None: ...
    def on_landmarks(self, lms: Landmarks, ff: FrameFeatures) -> None: ...
    def on_train_step(self, iteration: int, loss: float, psnr: float) -> None: ...
    def on_map(self, m: MapData, timings: dict) -> None: ...

    wants_images: bool = False  # keep the working images for on_frames


class _Progress:
    """Per-stage progress reporting; ``callback(stage, done, total)``."""

    def __init__(self, callback):
        cb = callback or (lambda *a: None)

        def report(stage, done, total):
            rebalance()  # thread pools follow the machine's load (favormap.threads)
            cb(stage, done, total)

        self.callback = report
        self.timings: dict[str, float] = {}

    @contextmanager
    def stage(self, name):
        t = time.perf_counter()
        yield
        self.timings[name] = round(time.perf_counter() - t, 3)


def track_frames(ff: FrameFeatures, config: BuildConfig) -> Tracks:
    """The build's tracking stage: the frames' features matched into tracks with ``config``'s settings."""
    return track_features(
        ff.without_state(),
        ff.cam_from_world,
        ff.cameras,
        config.min_track,
        config.match_window,
        config.max_epipolar_px,
        config.min_similarity,
        min_epipolar_px=default_max_epipolar(config.extractor),
    )


def refine_landmarks(lms: Landmarks, seq: Sequence, ff: FrameFeatures, config: BuildConfig) -> Landmarks:
    """The build's keypoint refinement (``config.refine_window``): each landmark's observations
    aligned through its local plane (triangulation.refine_observations, on the frames' grey images),
    then triangulated again."""
    grays = [frame_gray(seq, ff, f, config) for f in range(len(ff.features))]
    tracks = refine_observations(
        lms, grays, np.stack([c.K for c in ff.cameras]), ff.cam_from_world, config.refine_window
    )[0]
    return triangulate_tracks(tracks, ff, config)


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


def refine_mapping_poses(lms: Landmarks, ff: FrameFeatures, config: BuildConfig, epipolar_median_px: float):
    """The build's pose refinement (favormap.pose_refinement): bundle adjustment of the poses with every
    triangulated track, the camera centres held near the given ones by the error the measured pose noise
    implies (at least the extractor's keypoint precision)."""
    precision = default_max_epipolar(config.extractor)  # the extractor's keypoint precision (px)
    noise = max(precision, float(epipolar_median_px)) if np.isfinite(epipolar_median_px) else precision
    return refine_poses(lms, ff.cam_from_world, ff.cameras, noise, loss_px=precision)


def triangulate_tracks(tracks: Tracks, ff: FrameFeatures, config: BuildConfig) -> Landmarks:
    """The build's triangulation stage: every track that triangulates (before :func:`select_landmarks`)."""
    tri_cfg = TriangulationConfig(config.max_reproj_px, config.min_angle_deg, min_track=config.min_track)
    return triangulate(tracks, ff.cam_from_world, np.stack([c.K for c in ff.cameras]), tri_cfg)


def landmark_budget(
    lengths: np.ndarray,
    errors: np.ndarray,
    obs_landmark: np.ndarray,
    obs_frame: np.ndarray,
    max_landmarks: int,
    min_frame_landmarks: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Which landmarks a map keeps: a bool mask, and the kept ones' indices best first.

    The ``max_landmarks`` most persistent (longest track), best triangulated (lowest mean reprojection
    error) landmarks; then each mapping frame that sees fewer than ``min_frame_landmarks`` of them gets its
    best remaining ones up to that count (where its tracks allow). So the budget goes to the tracks
    that see the most, and no stretch of the path is left with too few landmarks to localize a query
    near it. ``obs_landmark``/``obs_frame``: the landmark and frame of every observation."""
    n = len(lengths)
    order = np.lexsort((errors, -np.asarray(lengths)))
    keep = np.zeros(n, bool)
    keep[order[:max_landmarks]] = True
    if min_frame_landmarks > 0 and n > max_landmarks and len(obs_frame):
        rank = np.empty(n, np.int64)
        rank[order] = np.arange(n)
        seen = np.bincount(obs_frame[keep[obs_landmark]], minlength=int(obs_frame.max()) + 1)
        cand = np.flatnonzero(~keep[obs_landmark])
        cand = cand[np.lexsort((rank[obs_landmark[cand]], obs_frame[cand]))]  # per frame, best first
        frames = obs_frame[cand]
        place = np.arange(len(cand)) - np.searchsorted(frames, frames)  # among the frame's candidates
        keep[obs_landmark[cand[place < min_frame_landmarks - seen[frames]]]] = True
    return keep, order[keep[order]]


def select_landmarks(lms: Landmarks, max_landmarks: int, min_frame_landmarks: int = 0) -> Landmarks:
    """The landmarks within the budget (:func:`landmark_budget`), best first."""
    if len(lms) <= max_landmarks:
        return lms
    _, order = landmark_budget(
        lms.tracks.lengths,
        lms.mean_reproj_error,
        lms.tracks.track_of_obs,
        lms.tracks.frame_idx,
        max_landmarks,
        min_frame_landmarks,
    )
    return lms.select(order)


def landmark_geometry(lms: Landmarks, cam_from_world: np.ndarray):
    """Viewing direction (unit, landmark -> cameras), angular radius (deg) and depth range of the
    training views of each landmark."""
    return view_geometry(lms.positions, lms.tracks.track_of_obs, camera_centers(cam_from_world)[lms.tracks.frame_idx])


# builds of more frames keep their features in a temporary feature cache file (build_map's feature_cache)
MEMORY_FRAMES = 300


def check_build_input(seq: Sequence, config: BuildConfig) -> None:
    """Every check that could refuse the map, run before the work: the sequence's cameras and poses
    against the map schema (what the writer checks after the training)."""
    from .mapfile.writer import check_frames

    if not seq.frames:
        raise SequenceError(f"sequence {seq.root} has no frames")
    try:
        check_patch(config.voxel.patch_size, config.voxel.patch_stride, bool(config.voxel.patch_interp))
    except ValueError as e:
        raise InputError(f"VoxelConfig: {e}") from None
    if config.match_window < 1 or not (config.max_epipolar_px is None or config.max_epipolar_px > 0):
        raise InputError(
            f"BuildConfig: match_window must be >= 1 and max_epipolar_px > 0 "
            f"(got {config.match_window}, {config.max_epipolar_px})"
        )
    if config.align_patches < 0 or config.align_patches > 64:
        raise InputError(f"BuildConfig: align_patches must be 0 (off) to 64 px, not {config.align_patches}")
    problems = check_frames(
        seq.cameras,
        [f.name for f in seq.frames],
        [f.camera_id for f in seq.frames],
        np.stack([f.cam_from_world for f in seq.frames]),
    )
    if problems:
        raise SequenceError(
            f"sequence {seq.root} cannot become a map: {problems[0]}"
            + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else "")
        )


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


def build_map(
    seq: Sequence,
    config: BuildConfig | None = None,
    progress: Callable | None = None,
    observer: BuildObserver | None = None,
    executor: Executor | None = None,
    ray: str | None = None,
    device: str = "cpu",
    feature_cache=None,
) -> MapData:
    """Run the whole map-building pipeline on a posed sequence. ``progress(stage, done, total)``
    reports progress; ``observer`` sees every stage's result (visualisation, debugging). ``device``
    ("cpu", "cuda", ...) is where voxel training and a torch extractor run; the map does not depend
    on it beyond floating-point noise (tests/test_cuda.py). An explicit ``executor`` decides devices
    itself (``LocalExecutor(device)``; Ray: the GPUs it assigns).

    Feature extraction (per frame), descriptor patches (per frame) and voxel training (per batch of
    ``config.train_batch`` landmarks) run on ``executor`` (default: this process). ``ray`` ("auto" or
    a cluster address) runs them as Ray tasks instead (:class:`favormap.distributed.RayExecutor`;
    ``pip install favormap[distributed]``); the map is the same either way.

    ``feature_cache``: where the frames' features live between the stages. A path: that HDF5 file
    (:mod:`favormap.features.cache`), kept and reused by later builds with the same extractor
    settings. None (default): in memory up to ``MEMORY_FRAMES`` frames, a temporary cache file above
    (removed at the end), so that memory does not grow with the sequence. False: in memory. The map
    is the same either way."""
    config = BuildConfig() if config is None else config
    check_build_input(seq, config)
    if ray is not None:
        if executor is not None:
            raise ValueError("build_map: give either executor or ray, not both")
        from .distributed import RayExecutor

        with RayExecutor(ray, gpus=device != "cpu") as ex:
            return build_map(seq, config, progress, observer, executor=ex, feature_cache=feature_cache)
    cacheable = feats_mod.extractor_class(config.extractor).can_cache()
    if feature_cache is None and len(seq.frames) > MEMORY_FRAMES and cacheable:
        with tempfile.TemporaryDirectory(prefix="favormap-features-") as tmp:
            return build_map(seq, config, progress, observer, executor, None, device, Path(tmp) / "features.h5")
    if feature_cache not in (None, False):
        with FeatureCache(feature_cache, config.extractor, config.max_keypoints, config.max_side) as cache:
            return _build(seq, config, progress, observer, executor, device, cache)
    return _build(seq, config, progress, observer, executor, device, None)


def _build(seq, config, progress, observer, executor, device, cache) -> MapData:
    if config.threads is not None:  # asked: the driver's pools and heap policy (a Ray task sets its own)
        thread_count(config.threads)
        # large temporaries (tracking's similarity blocks, the closed form's chunks) from reused heap blocks,
        # not fresh mappings faulted in page by page (favormap.heap)
        reuse_freed_blocks()
    if executor is None:  # this process: CPU stages on favormap.threads.thread_count() threads
        with LocalExecutor(device) as ex:
            return _build(seq, config, progress, observer, ex, device, cache)
    pr = _Progress(progress)
    obs = observer or BuildObserver()
    # the per-extractor defaults resolved (recorded in the provenance)
    config = replace(config, voxel=voxel_config_for(config.voxel, config.extractor))
    images = [] if obs.wants_images else None
    extractor = ExtractorSpec(config.extractor, config.max_keypoints)
    with pr.stage("extract"):
        ff = extract_sequence(seq, extractor, config.max_side, pr.callback, images, executor, cache)
    obs.on_frames(seq, ff, images)
    with pr.stage("track"):
        tracks = track_frames(ff, config)
        release_free_memory()
        pr.callback("track", 1, 1)
    obs.on_tracks(tracks, ff)
    if len(tracks) == 0:
        raise FavormapError(
            f"no feature tracks of length >= {config.min_track} in {seq.root}: too few frames, too little overlap, "
            "or wrong poses"
        )
    with pr.stage("triangulate"):
        all_lms = triangulate_tracks(tracks, ff, config)
        refinement = None
        if len(all_lms) and config.refine_poses:
            refinement = refine_mapping_poses(all_lms, ff, config, tracks.epipolar_median_px)
            ff = replace(ff, cam_from_world=refinement.cam_from_world)
            all_lms = triangulate_tracks(tracks, ff, config)
        if config.refine_window:
            all_lms = refine_landmarks(all_lms, seq, ff, config)
        lms = select_landmarks(all_lms, config.max_landmarks, config.min_frame_landmarks)
        n_tracks, n_triangulated = len(tracks), len(all_lms)
        epipolar_kept = tracks.epipolar_matches / max(tracks.matches, 1)
        epipolar_kept_3x = tracks.epipolar_matches_3x / max(tracks.matches, 1)
        epipolar_px, epipolar_median = tracks.max_epipolar_px, tracks.epipolar_median_px
        del tracks, all_lms  # every track's observations: only the selected landmarks' go on
        release_free_memory()
        pr.callback("triangulate", 1, 1)
    obs.on_landmarks(lms, ff)
    if len(lms) == 0:
        raise FavormapError("no landmark survived triangulation (check that the poses match the images)")
    with pr.stage("patches"):
        rays = training_rays(
            lms,
            ff,
            extractor,
            config.voxel.patch_size,
            config.voxel.box_factor,
            executor,
            pr.callback,
            config.voxel.patch_stride,
            config.voxel.patch_interp,
        )
    release_free_memory()
    with pr.stage("train"):
        grids = train_batches(rays, config.voxel, config.train_batch, executor, pr.callback)
    release_free_memory()  # the blocks training kept for reuse (favormap.heap)
    for it, loss, psnr in grids.history:  # the (landmark-weighted) training curve
        obs.on_train_step(it, loss, psnr)
    channels = rays.targets.shape[-1]
    view_dir, view_angle, depth_range = landmark_geometry(lms, ff.cam_from_world)
    mean_desc = track_mean_descriptors(
        rays, len(lms), config.voxel.patch_size, config.voxel.mean_patch, config.voxel.patch_stride
    )
    stats = {
        "frames": len(seq.frames),
        "frames_extracted": len(seq.frames) if ff.extracted is None else ff.extracted,
        "tracks": int(n_tracks),
        # shares of the mutual matches within the epipolar limit and 3x it (favormap.tracking.Tracks)
        "epipolar_kept": round(epipolar_kept, 4),
        "epipolar_kept_3x": round(epipolar_kept_3x, 4),  # within 3x the limit
        "max_epipolar_px": float(epipolar_px),  # the limit used: given, or measured
        "epipolar_measured": config.max_epipolar_px is None,
        # the right matches' median distance from their epipolar lines (px; measured limits only)
        **({"epipolar_median_px": round(epipolar_median, 3)} if epipolar_median == epipolar_median else {}),
        "triangulated": int(n_triangulated),
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
        **({"poses_refined": False} if refinement is None else refinement.stats()),
        "median_psnr": float(np.median(grids.psnr)),
        "median_cosine": float(np.median(grids.cosine)),
    }
    R = config.voxel.resolution
    m = MapData(
        extractor=config.extractor,
        channels=channels,
        grid_resolution=R,
        patch_size=config.voxel.patch_size,
        render_samples=config.voxel.samples,
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
        track_landmark=lms.tracks.track_of_obs.astype(np.int32),
        track_frame=lms.tracks.frame_idx.astype(np.int32),
        track_xy=lms.tracks.xy.astype(np.float32),
        track_patch=observation_patches(lms, seq, ff, config) if config.align_patches else None,
        provenance={
            "source": str(seq.root),
            "source_format": seq.format,
            "config": config.to_dict(),
            "localize_defaults": localize_defaults(config),
            "timings": pr.timings,
            "stats": stats,
            "training_history": grids.history,
            "executor": executor.describe(),
            "feature_cache": "memory" if cache is None else str(cache.path),
        },
    )
    obs.on_map(m, pr.timings)
    return m
