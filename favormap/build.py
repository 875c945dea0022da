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
from .build_result import (
    BuildLandmarks,
    BuildRun,
    TrackSummary,
    build_map_data,
    frame_gray,
    landmark_geometry,
    observation_patches,
    track_mean_descriptors,
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
from .features.base import check_patch
from .features.cache import FeatureCache
from .heap import release_free_memory, reuse_freed_blocks
from .io import Sequence
from .mapfile.model import MapData
from .pose_refinement import estimate_camera_rotation, poses_need_refinement, refine_poses
from .threads import rebalance, thread_count
from .tracking import Tracks, track_features
from .triangulation import Landmarks, refine_observations, triangulate
from .voxels import TrainingRays
from .voxels.batches import TrainTask, batch_bounds, rays_subset, train_batch, train_batches
from .voxels.config import VoxelGrids, voxel_config_for
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


def refine_mapping_poses(lms: Landmarks, ff: FrameFeatures, config: BuildConfig, epipolar_median_px: float):
    """The build's pose refinement (favormap.pose_refinement): bundle adjustment of the poses with every
    triangulated track, the camera centres held near the given ones by the error the measured pose noise
    implies (at least the extractor's keypoint precision)."""
    precision = default_max_epipolar(config.extractor)  # the extractor's keypoint precision (px)
    noise = max(precision, float(epipolar_median_px)) if np.isfinite(epipolar_median_px) else precision
    return refine_poses(lms, ff.cam_from_world, ff.cameras, noise, loss_px=precision)


def estimates_camera_rotation(config: BuildConfig, epipolar_median_px: float) -> bool:
    """Whether the build estimates the camera's rotation against the given poses (BuildConfig.camera_rotation;
    None: where the tracks' median epipolar distance exceeds the extractor's keypoint precision)."""
    if config.camera_rotation is not None:
        return bool(config.camera_rotation)
    return poses_need_refinement(epipolar_median_px, default_max_epipolar(config.extractor))


def triangulate_tracks(tracks: Tracks, ff: FrameFeatures, config: BuildConfig) -> Landmarks:
    """The build's triangulation stage: every track that triangulates (before :func:`select_landmarks`)."""
    return triangulate(tracks, ff.cam_from_world, np.stack([c.K for c in ff.cameras]), config.triangulation())


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
    extractor = ExtractorSpec(config.extractor, config.max_keypoints)
    ff = _extract_stage(seq, config, extractor, executor, cache, pr, obs)
    found = _landmark_stage(_track_stage(seq, ff, config, pr, obs), seq, ff, config, pr)
    obs.on_landmarks(found.lms, found.ff)
    if len(found.lms) == 0:
        raise FavormapError("no landmark survived triangulation (check that the poses match the images)")
    rays = _patch_stage(found, extractor, config, executor, pr)
    grids = _train_stage(rays, config, executor, pr, obs)
    run = BuildRun(pr.timings, executor.describe(), "memory" if cache is None else str(cache.path))
    m = build_map_data(seq, config, found, rays, grids, run)
    obs.on_map(m, pr.timings)
    return m


def _extract_stage(
    seq: Sequence,
    config: BuildConfig,
    extractor: ExtractorSpec,
    executor: Executor,
    cache: FeatureCache | None,
    pr: _Progress,
    obs: BuildObserver,
) -> FrameFeatures:
    """Every frame's features (and the working images, where the observer wants them)."""
    images = [] if obs.wants_images else None
    with pr.stage("extract"):
        ff = extract_sequence(seq, extractor, config.max_side, pr.callback, images, executor, cache)
    obs.on_frames(seq, ff, images)
    return ff


def _track_stage(seq: Sequence, ff: FrameFeatures, config: BuildConfig, pr: _Progress, obs: BuildObserver) -> Tracks:
    """The frames' features matched into tracks; refuses a sequence without any."""
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
    return tracks


def _landmark_stage(
    tracks: Tracks, seq: Sequence, ff: FrameFeatures, config: BuildConfig, pr: _Progress
) -> BuildLandmarks:
    """The tracks triangulated (with the poses refined and the keypoints aligned where asked) and the
    landmarks within the budget selected; only their observations go on."""
    with pr.stage("triangulate"):
        all_lms = triangulate_tracks(tracks, ff, config)
        refinement, rotation = None, None
        if len(all_lms) and config.refine_poses:
            refinement = refine_mapping_poses(all_lms, ff, config, tracks.epipolar_median_px)
            ff = replace(ff, cam_from_world=refinement.cam_from_world)
            all_lms = triangulate_tracks(tracks, ff, config)
        elif len(all_lms) and estimates_camera_rotation(config, tracks.epipolar_median_px):
            rotation = estimate_camera_rotation(
                all_lms,
                ff.cam_from_world,
                ff.cameras,
                loss_px=default_max_epipolar(config.extractor),
                order=tracks.frame_order,
            )
            if rotation.holds:
                ff = replace(ff, cam_from_world=rotation.camera_poses(ff.cam_from_world))
                all_lms = triangulate_tracks(tracks, ff, config)
        if config.refine_window:
            all_lms = refine_landmarks(all_lms, seq, ff, config)
        lms = select_landmarks(all_lms, config.max_landmarks, config.min_frame_landmarks)
        summary = TrackSummary.of(tracks, len(all_lms))
        del tracks, all_lms  # every track's observations: only the selected landmarks' go on
        release_free_memory()
        pr.callback("triangulate", 1, 1)
    return BuildLandmarks(lms, ff, refinement, summary, rotation)


def _patch_stage(
    found: BuildLandmarks, extractor: ExtractorSpec, config: BuildConfig, executor: Executor, pr: _Progress
) -> TrainingRays:
    """The training rays: every observation's descriptor patch."""
    vox = config.voxel
    with pr.stage("patches"):
        rays = training_rays(
            found.lms,
            found.ff,
            extractor,
            vox.patch_size,
            vox.box_factor,
            executor,
            pr.callback,
            vox.patch_stride,
            vox.patch_interp,
        )
    release_free_memory()
    return rays


def _train_stage(
    rays: TrainingRays, config: BuildConfig, executor: Executor, pr: _Progress, obs: BuildObserver
) -> VoxelGrids:
    """Every landmark's voxel grids, trained batch by batch on ``executor``."""
    with pr.stage("train"):
        grids = train_batches(rays, config.voxel, config.train_batch, executor, pr.callback)
    release_free_memory()  # the blocks training kept for reuse (favormap.heap)
    for it, loss, psnr in grids.history:  # the (landmark-weighted) training curve
        obs.on_train_step(it, loss, psnr)
    return grids
