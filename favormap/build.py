"""build: posed image sequence -> trained feature-voxel map (in memory; mapfile writes it).

Stages: extract -> track -> triangulate -> select -> patches -> train. Each stage hands one
dataclass to the next; ``build_map`` runs them and records timings and statistics.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import numpy as np

from . import features as feats_mod
from .errors import FavormapError, SequenceError
from .features import Extractor, Features, patch_offsets
from .geometry import camera_centers
from .io import Camera, Sequence, load_image
from .mapfile.model import MapData, new_landmark_ids
from .threads import configure_threads, rebalance
from .tracking import Tracks, track_features
from .triangulation import Landmarks, TriangulationConfig, triangulate
from .voxels import TrainingRays, VoxelConfig, train_voxels
from .voxels.train import PRIOR_MEAN_DEG, PRIOR_MEAN_DEG_OTHER


@dataclass
class BuildConfig:
    extractor: str = "sift"  # tools/bench_accuracy.py: fox hold-out 0.0021 vs 0.0052 units (xfeat), extrapolation 0.0058 vs 0.054
    max_keypoints: int = 2048
    max_side: int = 640  # images are downscaled so that max(w, h) <= max_side (0: keep)
    min_track: int = 5
    match_window: int = 3
    max_epipolar_px: float = 2.0
    min_similarity: float = 0.7
    max_reproj_px: float = 5.0
    min_angle_deg: float = 1.0
    max_landmarks: int = 1500
    voxel: VoxelConfig = field(default_factory=VoxelConfig)
    threads: int | None = None  # CPU threads for torch/OpenCV (None: favormap.threads' rule); not stored in the map

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("threads")
        return d


@dataclass
class FrameFeatures:
    """Stage boundary after extraction: features plus the working (undistorted, resized) cameras."""

    features: list[Features]
    cameras: list[Camera]  # working pinhole camera per frame
    cam_from_world: np.ndarray  # (M, 4, 4)


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


def extract_sequence(seq: Sequence, extractor: Extractor, max_side: int, progress=None, keep_images: list | None = None) -> FrameFeatures:
    features, cams = [], []
    for i, fr in enumerate(seq.frames):
        img, wcam = load_image(fr.image_path, seq.cameras[fr.camera_id], max_side)
        features.append(extractor.extract(img))
        cams.append(wcam)
        if keep_images is not None:
            keep_images.append(img)
        if progress:
            progress("extract", i + 1, len(seq.frames))
    return FrameFeatures(features, cams, np.stack([f.cam_from_world for f in seq.frames]))


def select_landmarks(lms: Landmarks, max_landmarks: int) -> Landmarks:
    """Keep the most persistent (longest track), best triangulated (lowest error) landmarks."""
    if len(lms) <= max_landmarks:
        return lms
    order = np.lexsort((lms.mean_reproj_error, -lms.tracks.lengths))
    return lms.select(order[:max_landmarks])


def training_rays(lms: Landmarks, ff: FrameFeatures, extractor: Extractor, patch_size: int,
                  box_factor: float | None = None) -> TrainingRays:
    """Descriptor patches S x S around the projection of each landmark in each of its frames, and
    the viewing rays of their pixels. One ``extractor.sample`` call per frame.

    Voxel side of landmark j: ``box_factor * min_i l_ij / f_i`` (paper eq. 2 uses the patch size S,
    the reference code 12 for S = 7); ``box_factor`` None means S."""
    tr = lms.tracks
    tid = tr.track_of_obs
    fi = tr.frame_idx
    T = ff.cam_from_world
    Ks = np.stack([c.K for c in ff.cameras])
    X = lms.positions[tid]
    Xc = np.einsum("oij,oj->oi", T[fi, :3, :3], X) + T[fi, :3, 3]
    uv = np.einsum("oij,oj->oi", Ks[fi], Xc)
    uv = uv[:, :2] / uv[:, 2:3]
    offs = patch_offsets(patch_size)
    pix = uv[:, None, :] + offs[None]  # (O, P, 2)
    P = len(offs)
    targets = np.zeros((len(tid), P, extractor.channels), np.float32)
    order = np.argsort(fi, kind="stable")
    bounds = np.searchsorted(fi[order], np.arange(len(ff.features) + 1))
    for f in range(len(ff.features)):
        sel = order[bounds[f] : bounds[f + 1]]
        if len(sel):
            targets[sel] = extractor.sample(ff.features[f], pix[sel].reshape(-1, 2)).reshape(len(sel), P, -1)
    # ray directions in world
    hom = np.concatenate([pix, np.ones(pix.shape[:2] + (1,))], -1)
    d_cam = np.einsum("oij,opj->opi", np.linalg.inv(Ks)[fi], hom)
    d_world = np.einsum("oji,opj->opi", T[fi, :3, :3], d_cam)
    centers = camera_centers(T)[fi]
    # voxel size (paper eq. 2): s_j = min_i factor * l_ij / f
    focal = 0.5 * (Ks[fi, 0, 0] + Ks[fi, 1, 1])
    dist = np.linalg.norm(X - centers, axis=1)
    sizes = np.full(len(lms), np.inf)
    np.minimum.at(sizes, tid, (patch_size if box_factor is None else box_factor) * dist / focal)
    return TrainingRays(lms.positions, sizes, tid.astype(np.int64), centers, d_world.astype(np.float32), targets)


def landmark_geometry(lms: Landmarks, cam_from_world: np.ndarray):
    """Viewing direction (unit, landmark -> cameras), angular radius (deg) and depth range of the
    training views of each landmark."""
    tid = lms.tracks.track_of_obs
    c = camera_centers(cam_from_world)[lms.tracks.frame_idx]
    v = c - lms.positions[tid]
    dist = np.linalg.norm(v, axis=1)
    u = v / np.maximum(dist[:, None], 1e-12)
    mean = np.zeros((len(lms), 3))
    np.add.at(mean, tid, u)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    ang = np.degrees(np.arccos(np.clip(np.sum(u * mean[tid], 1), -1, 1)))
    amax = np.zeros(len(lms))
    np.maximum.at(amax, tid, ang)
    dmin = np.full(len(lms), np.inf)
    dmax = np.zeros(len(lms))
    np.minimum.at(dmin, tid, dist)
    np.maximum.at(dmax, tid, dist)
    return mean, amax, np.stack([dmin, dmax], 1)


def check_build_input(seq: Sequence, config: BuildConfig) -> None:
    """Every check that could refuse the map, run before the work: the sequence's cameras and poses
    against the map schema (what the writer checks after the training)."""
    from .mapfile.writer import check_frames

    if not seq.frames:
        raise SequenceError(f"sequence {seq.root} has no frames")
    problems = check_frames(seq.cameras, [f.name for f in seq.frames], [f.camera_id for f in seq.frames],
                            np.stack([f.cam_from_world for f in seq.frames]))
    if problems:
        raise SequenceError(f"sequence {seq.root} cannot become a map: {problems[0]}"
                            + (f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""))


def build_map(seq: Sequence, config: BuildConfig = BuildConfig(), progress: Callable | None = None,
              observer: BuildObserver | None = None) -> MapData:
    """Run the whole map-building pipeline on a posed sequence. ``progress(stage, done, total)``
    reports progress; ``observer`` sees every stage's result (visualisation, debugging)."""
    check_build_input(seq, config)
    configure_threads(config.threads)
    pr = _Progress(progress)
    obs = observer or BuildObserver()
    if config.voxel.prior_mean_deg is None:  # resolve the per-extractor default (recorded in the provenance)
        config = replace(config, voxel=replace(config.voxel, prior_mean_deg=PRIOR_MEAN_DEG.get(config.extractor, PRIOR_MEAN_DEG_OTHER)))
    images = [] if obs.wants_images else None
    extractor = feats_mod.create(config.extractor, max_keypoints=config.max_keypoints, device=config.voxel.device if config.voxel.device != "cpu" else None)
    with pr.stage("extract"):
        ff = extract_sequence(seq, extractor, config.max_side, pr.callback, images)
    obs.on_frames(seq, ff, images)
    with pr.stage("track"):
        tracks = track_features(ff.features, ff.cam_from_world, ff.cameras, config.min_track, config.match_window,
                                config.max_epipolar_px, config.min_similarity)
        pr.callback("track", 1, 1)
    obs.on_tracks(tracks, ff)
    if len(tracks) == 0:
        raise FavormapError(f"no feature tracks of length >= {config.min_track} in {seq.root}: too few frames, too little overlap, or wrong poses")
    with pr.stage("triangulate"):
        tri_cfg = TriangulationConfig(config.max_reproj_px, config.min_angle_deg, min_track=config.min_track)
        Ks = np.stack([c.K for c in ff.cameras])
        all_lms = triangulate(tracks, ff.cam_from_world, Ks, tri_cfg)
        lms = select_landmarks(all_lms, config.max_landmarks)
        pr.callback("triangulate", 1, 1)
    obs.on_landmarks(lms, ff)
    if len(lms) == 0:
        raise FavormapError("no landmark survived triangulation (check that the poses match the images)")
    with pr.stage("patches"):
        rays = training_rays(lms, ff, extractor, config.voxel.patch_size, config.voxel.box_factor)
        pr.callback("patches", 1, 1)
    with pr.stage("train"):
        def on_step(it, loss, psnr):
            pr.callback("train", it + 1, config.voxel.iterations)
            obs.on_train_step(it, loss, psnr)

        grids = train_voxels(rays, config.voxel, progress=on_step)
        pr.callback("train", config.voxel.iterations, config.voxel.iterations)
    view_dir, view_angle, depth_range = landmark_geometry(lms, ff.cam_from_world)
    mean_desc = np.zeros((len(lms), extractor.channels), np.float64)
    np.add.at(mean_desc, rays.obs_landmark, rays.targets.mean(1))
    mean_desc /= np.maximum(np.linalg.norm(mean_desc, axis=1, keepdims=True), 1e-12)
    stats = {
        "frames": len(seq.frames),
        "tracks": int(len(tracks)),
        "triangulated": int(len(all_lms)),
        "landmarks": int(len(lms)),
        "mean_track_length": float(lms.tracks.lengths.mean()),
        "median_reproj_error_px": float(np.median(lms.reproj_errors)),
        "median_psnr": float(np.median(grids.psnr)),
        "median_cosine": float(np.median(grids.cosine)),
    }
    R = config.voxel.resolution
    m = MapData(
        extractor=config.extractor,
        channels=extractor.channels,
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
        provenance={"source": str(seq.root), "source_format": seq.format, "config": config.to_dict(),
                    "timings": pr.timings, "stats": stats, "training_history": grids.history},
    )
    obs.on_map(m, pr.timings)
    return m
