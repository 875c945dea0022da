"""build: posed image sequence -> trained feature-voxel map (in memory; mapfile writes it).

Stages: extract -> track -> triangulate -> select -> patches -> train. Each stage hands one
dataclass to the next; ``build_map`` runs them and records timings and statistics.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable
from collections.abc import Sequence as SequenceABC
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields, is_dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from . import features as feats_mod
from .errors import FavormapError, InputError, SequenceError
from .executor import Executor, LocalExecutor
from .features import Extractor, Features, patch_offsets
from .features.base import check_patch, patch_interpolation
from .features.cache import FeatureCache, source_stamp
from .geometry import camera_centers, project, sum_by_group, unproject, view_geometry
from .heap import release_free_memory, reuse_freed_blocks
from .io import Camera, Sequence
from .io.images import decode_and_prepare, patches_around, read_image_bytes
from .mapfile.model import MapData, median_landmark_reproj_error, new_landmark_ids
from .threads import rebalance, thread_count
from .tracking import Tracks, track_features
from .triangulation import Landmarks, TriangulationConfig, refine_observations, triangulate
from .voxels import TrainingRays, VoxelConfig, VoxelGrids, train_voxels
from .voxels.config import voxel_config_for


def default_max_epipolar(extractor: str) -> float:
    """The least epipolar limit of tracking for ``extractor`` (its policy's keypoint precision, px)."""
    return feats_mod.policy_of(extractor).keypoint_precision_px


def default_align_patches(extractor: str) -> int:
    """The stored observation patches' radius a build of ``extractor`` uses when none is given (0: none)."""
    return feats_mod.policy_of(extractor).align_patches


# BuildConfig.exact_poses: the track alignment's window (px) and the stored observation patches' radius
EXACT_POSES_REFINE_WINDOW = 9
EXACT_POSES_PATCHES = 20


def localize_defaults(config: BuildConfig) -> dict:
    """What a map built with ``config`` asks of the localizer unless told otherwise (stored in the map's
    provenance as ``localize_defaults``; LocalizeConfig fields left None follow it): the keypoint alignment
    where the poses are exact or the extractor's policy asks for it, with the stored patches it needs."""
    aligning = feats_mod.policy_of(config.extractor).align_patches > 0
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
    min_track: int = 3  # frames a track must span to become a landmark
    match_window: int = 10  # each frame is matched with this many next frames
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
    max_reproj_px: float = 5.0  # a landmark's largest reprojection error in its observations
    min_angle_deg: float = 1.0  # a landmark's least triangulation angle
    max_landmarks: int = 3000  # the longest tracks are kept
    # landmarks trained together in one task (seeded voxel.seed + batch index): the map depends on
    # this, not on who runs the batches (LocalExecutor or Ray workers)
    train_batch: int = 1024
    voxel: VoxelConfig | None = None  # None: the preset ExtractorPolicy.training_quality names
    # CPU threads for torch/OpenCV: None leaves the process's pools (and heap policy) alone; "auto" applies
    # favormap.threads' rule, a number fixes them (favormap.threads.thread_count); not stored in the map
    threads: int | str | None = None

    def __post_init__(self):
        if self.voxel is None:
            self.voxel = VoxelConfig.preset(feats_mod.policy_of(self.extractor).training_quality)
        if self.align_patches is None:
            self.align_patches = default_align_patches(self.extractor)
        if self.exact_poses:
            self.refine_window = self.refine_window or EXACT_POSES_REFINE_WINDOW
            self.align_patches = self.align_patches or EXACT_POSES_PATCHES

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("threads")
        return d


@dataclass
class FrameFeatures:
    """Stage boundary after extraction: features plus the working (undistorted, resized) cameras."""

    features: SequenceABC[Features]  # a list, or the frames of a FeatureCache (read on access)
    cameras: list[Camera]  # working pinhole camera per frame
    cam_from_world: np.ndarray  # (M, 4, 4)
    extracted: int | None = None  # frames extracted by this build (None: all; fewer from a feature cache)

    def without_state(self) -> SequenceABC[Features]:
        """The features without the sampling state where that saves reading (tracking needs none)."""
        f = self.features
        return f.without_state() if hasattr(f, "without_state") else f


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


@dataclass(frozen=True)
class ExtractorSpec:
    """A picklable recipe for an extractor (tasks on other processes or machines make their own)."""

    name: str
    max_keypoints: int = 2048

    def create(self, device: str | None = None) -> Extractor:
        """The extractor on ``device`` (None or "cpu": the CPU)."""
        return _cached_extractor(self.name, self.max_keypoints, None if device in (None, "cpu") else device)

    @property
    def uses_device(self) -> bool:
        """Whether the extractor runs on a torch device (a GPU helps)."""
        return bool(getattr(feats_mod.extractor_class(self.name), "uses_device", False))

    @property
    def samples_on_device(self) -> bool:
        """Whether sampling descriptors (the training patches) can run on a GPU (Extractor.samples_on_device)."""
        return bool(getattr(feats_mod.extractor_class(self.name), "samples_on_device", False))


@lru_cache(maxsize=64)
def _cached_extractor(name: str, max_keypoints: int, device: str | None, thread: int = 0) -> Extractor:
    return feats_mod.create(name, max_keypoints=max_keypoints, device=device)


def _extractor(ex: Extractor | ExtractorSpec, device: str | None = None) -> Extractor:
    if not isinstance(ex, ExtractorSpec):
        return ex
    if ex.uses_device:  # a torch model: one per device, shared by threads (inference does not change it)
        return ex.create(device)
    # OpenCV's extractor objects: one per thread (LocalExecutor's pool), they are cheap to create
    on = None if device in (None, "cpu") else device  # SIFT on a GPU: its patch descriptors computed there
    return _cached_extractor(ex.name, ex.max_keypoints, on, threading.get_ident())


def _on_cpu(x):
    """Torch tensors in a (nested tuple/list/dataclass of) extractor state moved to the CPU, so that a
    result computed on a GPU worker can be read on a machine without one."""
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, (tuple, list)):
        return type(x)(_on_cpu(v) for v in x)
    if is_dataclass(x) and not isinstance(x, type):
        return replace(x, **{f.name: _on_cpu(getattr(x, f.name)) for f in fields(x) if f.init})
    return x


@dataclass
class ExtractTask:
    """One frame to extract: the image file's bytes (workers need no access to the sequence)."""

    name: str  # the image path, for messages
    data: bytes
    camera: Camera
    max_side: int
    extractor: Extractor | ExtractorSpec
    keep_image: bool = False


@dataclass
class ExtractedFrame:
    features: Features
    camera: Camera  # working pinhole camera
    image: np.ndarray | None = None  # the working image, when asked for


def extract_frame(task: ExtractTask, device: str | None = None, report=None) -> ExtractedFrame:
    img, cam = decode_and_prepare(task.data, task.name, task.camera, task.max_side)
    f = _extractor(task.extractor, device).extract(img)
    if f.dense is not None:
        f.dense = _on_cpu(f.dense)
    return ExtractedFrame(f, cam, img if task.keep_image else None)


# sequences longer than this keep their features in a temporary on-disk cache (build_map's feature_cache)
MEMORY_FRAMES = 300
MAP_CHUNK = 64  # tasks per executor.map call of a streamed stage (results held at once)


def map_into(executor: Executor, fn, tasks, total: int, sink, gpu: bool = False, progress=None, chunk: int = MAP_CHUNK):
    """``executor.map_each`` over ``tasks`` in chunks of ``chunk`` tasks, handing each result to
    ``sink(i, result)`` (in order): at most one chunk of results is ever held (none by an executor
    that hands each over as it completes)."""
    it = iter(tasks)
    done = 0
    while done < total:
        block = [t for _, t in zip(range(min(chunk, total - done)), it)]
        if not block:
            break
        off = done
        report = (lambda d, off=off: progress(off + d)) if progress else None
        executor.map_each(fn, block, len(block), lambda k, r, off=off: sink(off + k, r), gpu=gpu, progress=report)
        done += len(block)
        del block


def _image_key(path) -> str:
    return str(Path(path).resolve())


def extract_sequence(
    seq: Sequence,
    extractor: Extractor | ExtractorSpec,
    max_side: int,
    progress=None,
    keep_images: list | None = None,
    executor: Executor | None = None,
    cache: FeatureCache | None = None,
) -> FrameFeatures:
    """Features of every frame (one task per frame; the image bytes are read here, lazily).

    With ``cache``, each frame's features go to the cache as they arrive and the result reads them
    back from it on access (memory stays flat in the number of frames); images the cache already
    holds (same file size and time) are not extracted again."""
    executor = executor or LocalExecutor()
    gpu = isinstance(extractor, ExtractorSpec) and extractor.uses_device
    poses = np.stack([f.cam_from_world for f in seq.frames])
    if cache is None:
        todo = list(seq.frames)
    else:
        keys = [_image_key(fr.image_path) for fr in seq.frames]
        todo, stamps, seen = [], [], set()
        for fr, k in zip(seq.frames, keys):
            stamp = source_stamp(fr.image_path)  # before the bytes are read (a file changed meanwhile is redone)
            if k not in seen and not cache.has(k, stamp):
                todo.append(fr)
                stamps.append(stamp)
            seen.add(k)
    tasks = (
        ExtractTask(
            str(fr.image_path),
            read_image_bytes(fr.image_path),
            seq.cameras[fr.camera_id],
            max_side,
            extractor,
            keep_images is not None and cache is None,
        )
        for fr in todo
    )
    n = len(todo)
    results: list = []

    def sink(i, r: ExtractedFrame):
        if cache is None:
            results.append(r)
        else:
            cache.put(_image_key(todo[i].image_path), r.features, r.camera, stamps[i])

    report = (lambda d: progress("extract", int(d), n)) if progress else None
    map_into(executor, extract_frame, tasks, n, sink, gpu, report)
    if cache is None:
        if keep_images is not None:
            keep_images.extend(r.image for r in results)
        return FrameFeatures([r.features for r in results], [r.camera for r in results], poses)
    if keep_images is not None:  # (an observer that shows the images: decoded again, not cached)
        keep_images.extend(
            decode_and_prepare(None, fr.image_path, seq.cameras[fr.camera_id], max_side)[0] for fr in seq.frames
        )
    return FrameFeatures(cache.view(keys), [cache.camera(k) for k in keys], poses, extracted=n)


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


def triangulate_tracks(tracks: Tracks, ff: FrameFeatures, config: BuildConfig) -> Landmarks:
    """The build's triangulation stage: every track that triangulates (before :func:`select_landmarks`)."""
    tri_cfg = TriangulationConfig(config.max_reproj_px, config.min_angle_deg, min_track=config.min_track)
    return triangulate(tracks, ff.cam_from_world, np.stack([c.K for c in ff.cameras]), tri_cfg)


def select_landmarks(lms: Landmarks, max_landmarks: int) -> Landmarks:
    """Keep the most persistent (longest track), best triangulated (lowest error) landmarks."""
    if len(lms) <= max_landmarks:
        return lms
    order = np.lexsort((lms.mean_reproj_error, -lms.tracks.lengths))
    return lms.select(order[:max_landmarks])


@dataclass
class PatchLayout:
    """How a frame's samples become its observations' S x S training patches (P = S * S pixels): the
    extractor describes ``described`` pixels per observation, every pixel when ``blend`` is None;
    else patch pixel ``copied[k]`` copies described pixel ``source[k]`` and the pixels ``blended``
    are ``blend`` (len(blended), described) times the described ones, L2-normalised
    (:func:`favormap.features.base.patch_interpolation`)."""

    pixels: int
    described: int
    copied: np.ndarray | None = None
    source: np.ndarray | None = None
    blended: np.ndarray | None = None
    blend: np.ndarray | None = None

    @classmethod
    def interpolated(cls, weights: np.ndarray) -> PatchLayout:
        copied = np.flatnonzero(weights.max(1) == 1.0)
        blended = np.setdiff1d(np.arange(len(weights)), copied)
        return cls(len(weights), weights.shape[1], copied, weights[copied].argmax(1), blended, weights[blended])

    def assemble(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(o * described, C) samples -> the (o, P, C) float16 patches (TrainingRays.targets) and
        their (o, C) float32 means taken before the rounding (TrainingRays.target_means)."""
        d = samples.reshape(-1, self.described, samples.shape[-1])
        if self.blend is None:
            full = d
        else:
            b = np.matmul(self.blend, d)
            norm = np.sqrt(np.einsum("opc,opc->op", b, b))
            b /= np.maximum(norm, 1e-12, out=norm)[..., None]
            full = np.empty((len(d), self.pixels, d.shape[-1]), np.float32)
            full[:, self.copied], full[:, self.blended] = d[:, self.source], b
        import torch  # its float16 conversion (F16C): the same bits as NumPy's, 18x faster (16 -> 0.9 ms per fox frame)

        return torch.from_numpy(np.ascontiguousarray(full)).half().numpy(), full.mean(1, dtype=np.float32)


@dataclass
class PatchTask:
    """Descriptor samples at ``points`` (n, 2) of one frame (with ``layout``: its training patches)."""

    extractor: Extractor | ExtractorSpec
    features: Features
    points: np.ndarray
    layout: PatchLayout | None = None


def sample_patches(task: PatchTask, device: str | None = None, report=None) -> np.ndarray:
    return _extractor(task.extractor, device or "cpu").sample(task.features, task.points)


def patch_targets(task: PatchTask, device: str | None = None, report=None) -> tuple[np.ndarray, np.ndarray]:
    """A frame's training patches, float16, and their float32 means: :meth:`PatchLayout.assemble` of
    its samples, in the task (on the executor's threads or workers, not in the driver)."""
    return task.layout.assemble(sample_patches(task, device, report))


def training_rays(
    lms: Landmarks,
    ff: FrameFeatures,
    extractor: Extractor | ExtractorSpec,
    patch_size: int,
    box_factor: float | None = None,
    executor: Executor | None = None,
    progress=None,
    patch_stride: int = 1,
    patch_interp: bool = False,
) -> TrainingRays:
    """Descriptor patches S x S around the projection of each landmark in each of its frames (every
    ``patch_stride``-th pixel: features.patch_offsets), and the viewing rays of their pixels. One
    ``extractor.sample`` task per frame. With ``patch_interp`` the extractor describes only the
    pixels :func:`favormap.features.base.patch_interpolation` picks (25 of 49 for S = 7) and the
    others are interpolated bilinearly from them (then L2-normalised, as every sampled descriptor).

    Voxel side of landmark j: ``box_factor * min_i l_ij / f_i`` (paper eq. 2 uses the patch size S,
    the reference code 12 for S = 7); ``box_factor`` None means S."""
    tr = lms.tracks
    tid = tr.track_of_obs
    fi = tr.frame_idx
    T = ff.cam_from_world
    Ks = np.stack([c.K for c in ff.cameras])
    X = lms.positions[tid]
    uv = project(Ks[fi], T[fi], X)
    offs = patch_offsets(patch_size, patch_stride)
    pix = uv[:, None, :] + offs[None]  # (O, P, 2)
    P = len(offs)
    if patch_interp:
        check_patch(patch_size, patch_stride, interp=True)
        described, weights = patch_interpolation(patch_size)
        spix = uv[:, None, :] + described[None]  # (O, Pd, 2): the pixels the extractor describes
        layout = PatchLayout.interpolated(weights)
    else:
        spix, layout = pix, PatchLayout(P, P)
    order = np.argsort(fi, kind="stable")
    bounds = np.searchsorted(fi[order], np.arange(len(ff.features) + 1))
    # the frames with most observations first: the pool's threads then finish together (the last
    # tasks are the shortest) instead of one thread describing a large frame while the other idles
    sizes = np.diff(bounds)
    frames = [int(f) for f in np.argsort(-sizes, kind="stable") if sizes[f] > 0]
    tasks = (
        PatchTask(extractor, ff.features[f], spix[order[bounds[f] : bounds[f + 1]]].reshape(-1, 2), layout)
        for f in frames
    )
    n = len(frames)
    executor = executor or LocalExecutor()
    held: list[np.ndarray] = []  # the (O, P, C) targets and (O, C) means, made when the first frame's arrive

    def sink(k, result):
        full, mean = result
        if not held:
            held.append(np.zeros((len(tid), P, full.shape[-1]), np.float16))  # TrainingRays.targets
            held.append(np.zeros((len(tid), full.shape[-1]), np.float32))  # and their patch means
        f = frames[k]
        sel = order[bounds[f] : bounds[f + 1]]
        held[0][sel], held[1][sel] = full, mean

    map_into(
        executor,
        patch_targets,
        tasks,
        n,
        sink,
        # on a GPU where the extractor samples there (SIFT), else CPU tasks on the executor's threads
        gpu=isinstance(extractor, ExtractorSpec) and extractor.samples_on_device and executor.has_gpu,
        progress=(lambda d: progress("patches", int(d), n)) if progress else None,
    )
    targets, means = held if held else (np.zeros((len(tid), P, 0), np.float16), np.zeros((len(tid), 0), np.float32))
    # ray directions in world
    d_cam = unproject(Ks[fi][:, None], pix)
    d_world = np.einsum("oji,opj->opi", T[fi, :3, :3], d_cam)
    centers = camera_centers(T)[fi]
    # voxel size (paper eq. 2): s_j = min_i factor * l_ij / f
    focal = 0.5 * (Ks[fi, 0, 0] + Ks[fi, 1, 1])
    dist = np.linalg.norm(X - centers, axis=1)
    sizes = np.full(len(lms), np.inf)
    np.minimum.at(sizes, tid, (patch_size if box_factor is None else box_factor) * dist / focal)
    return TrainingRays(lms.positions, sizes, tid.astype(np.int64), centers, d_world.astype(np.float32), targets, means)


@dataclass
class TrainTask:
    """Landmarks to train: one batch or several consecutive ones (``seed_blocks``: their sizes, batch k
    of the task drawing from seed ``config.seed + k``; ``config.seed`` already the first batch's)."""

    rays: TrainingRays
    config: VoxelConfig
    seed_blocks: tuple[int, ...] | None = None


def train_batch(task: TrainTask, device: str | None = None, report=None) -> VoxelGrids:
    cfg = task.config
    iters = cfg.iterations
    g = train_voxels(
        task.rays,
        cfg,
        progress=(lambda it, loss, psnr: report((it + 1) / iters)) if report else None,
        device=device or "cpu",
        seed_blocks=task.seed_blocks,
    )
    return VoxelGrids(g.descriptors.cpu(), g.density.cpu(), g.psnr, g.cosine, g.history)


def batch_bounds(n_landmarks: int, batch: int) -> np.ndarray:
    """Landmark index bounds of the training batches: ceil(L / batch) batches of near-equal size."""
    nb = max(1, -(-n_landmarks // max(1, batch)))
    return np.round(np.linspace(0, n_landmarks, nb + 1)).astype(int)


def rays_subset(rays: TrainingRays, lo: int, hi: int) -> TrainingRays:
    """The training data of landmarks lo..hi-1 (landmark indices renumbered from 0): views of the
    arrays where the observations are sorted by landmark (as the build makes them), else copies."""
    ol = rays.obs_landmark
    if np.all(ol[1:] >= ol[:-1]):
        first, last = np.searchsorted(ol, [lo, hi])
        sel = slice(int(first), int(last))
    else:
        sel = (ol >= lo) & (ol < hi)
    return TrainingRays(
        rays.centers[lo:hi],
        rays.sizes[lo:hi],
        rays.obs_landmark[sel] - lo,
        rays.obs_origin[sel],
        rays.ray_dirs[sel],
        rays.targets[sel],
        None if rays.target_means is None else rays.target_means[sel],
    )


def train_batches(
    rays: TrainingRays, cfg: VoxelConfig, batch: int, executor: Executor | None = None, progress=None
) -> VoxelGrids:
    """All landmarks' voxels, trained in batches of ``batch`` landmarks (batch b seeded ``cfg.seed + b``;
    one batch is exactly ``train_voxels(rays, cfg)``). History: landmark-weighted mean over the batches.

    The executor may run several consecutive batches as one task (``Executor.train_group``: a local
    GPU takes up to 16 at once); each batch still draws its own random rays, so the grids are the
    same either way up to floating-point rounding (tests/test_core.py, tests/test_cuda.py)."""
    executor = executor or LocalExecutor()
    bounds = batch_bounds(len(rays.centers), batch)
    nb = len(bounds) - 1
    per = max(1, int(executor.train_group()))
    starts = list(range(0, nb, per))
    ends = [min(nb, b + per) for b in starts]
    tasks = (
        TrainTask(
            rays_subset(rays, bounds[b0], bounds[b1]),
            replace(cfg, seed=cfg.seed + b0),
            tuple(int(n) for n in np.diff(bounds[b0 : b1 + 1])) if b1 - b0 > 1 else None,
        )
        for b0, b1 in zip(starts, ends)
    )
    total = nb * cfg.iterations

    def report(d):  # d tasks done (fractional) -> batches done, in iterations
        k = min(int(d), len(starts) - 1)
        progress("train", int((starts[k] + (d - k) * (ends[k] - starts[k])) * cfg.iterations), total)

    parts = executor.map(train_batch, tasks, len(starts), gpu=True, progress=report if progress else None)
    bounds = bounds[[*starts, nb]]  # the tasks' landmark bounds
    w = np.diff(bounds) / bounds[-1]
    history = [
        (
            it,
            float(sum(wi * p.history[k][1] for wi, p in zip(w, parts))),
            float(sum(wi * p.history[k][2] for wi, p in zip(w, parts))),
        )
        for k, (it, _, _) in enumerate(parts[0].history)
    ]
    return VoxelGrids(
        torch.cat([p.descriptors for p in parts]),
        torch.cat([p.density for p in parts]),
        np.concatenate([p.psnr for p in parts]),
        np.concatenate([p.cosine for p in parts]),
        history,
    )


def landmark_geometry(lms: Landmarks, cam_from_world: np.ndarray):
    """Viewing direction (unit, landmark -> cameras), angular radius (deg) and depth range of the
    training views of each landmark."""
    return view_geometry(lms.positions, lms.tracks.track_of_obs, camera_centers(cam_from_world)[lms.tracks.frame_idx])


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
        if config.refine_window:
            all_lms = refine_landmarks(all_lms, seq, ff, config)
        lms = select_landmarks(all_lms, config.max_landmarks)
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
        "mean_track_length": float(lms.tracks.lengths.mean()),
        # one definition with `favormap info` (Map.info): the median over landmarks of each landmark's mean
        # reprojection error over its observations, as stored (float32) in landmarks/reproj_error
        "median_reproj_error_px": median_landmark_reproj_error(lms.mean_reproj_error.astype(np.float32)),
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
