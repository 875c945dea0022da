"""Training data of the voxels: the S x S descriptor patches around every observation of every landmark,
sampled on an executor's workers, as rays (:class:`favormap.voxels.TrainingRays`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..executor import Executor, LocalExecutor
from ..extraction import ExtractorSpec, FrameFeatures, _extractor, map_into
from ..features import Extractor, Features, patch_offsets
from ..features.base import check_patch, patch_interpolation
from ..geometry import camera_centers, project, unproject
from ..triangulation import Landmarks
from .config import TrainingRays


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
    P = len(offs)
    if patch_interp:
        check_patch(patch_size, patch_stride, interp=True)
        described, weights = patch_interpolation(patch_size)
        spix = uv[:, None, :] + described[None]  # (O, Pd, 2): the pixels the extractor describes
        layout = PatchLayout.interpolated(weights)
    else:
        spix, layout = uv[:, None, :] + offs[None], PatchLayout(P, P)  # (O, P, 2)
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
    centers, d_world, reach = patch_rays(lms.positions, tid, fi, Ks, T, patch_size, patch_stride, uv)
    sizes = voxel_sizes(reach, tid, len(lms), patch_size if box_factor is None else box_factor)
    return TrainingRays(lms.positions, sizes, tid.astype(np.int64), centers, d_world, targets, means)


def patch_rays(
    positions: np.ndarray,
    obs_landmark: np.ndarray,
    frame_idx: np.ndarray,
    Ks: np.ndarray,
    cam_from_world: np.ndarray,
    patch_size: int,
    patch_stride: int = 1,
    uv: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The geometry of the training patches of observations (landmark ``obs_landmark``, frame
    ``frame_idx``): each observation's camera centre (O, 3), the world directions (O, P, 3) float32
    of its patch pixels around the landmark's projection, and the landmark's distance in focal
    lengths (O,), from which :func:`voxel_sizes` takes the voxel side. ``uv``: the observations' landmark
    projections (O, 2), when the caller has them already."""
    X = positions[obs_landmark]
    T, K = cam_from_world[frame_idx], Ks[frame_idx]
    uv = project(K, T, X) if uv is None else uv
    pix = uv[:, None, :] + patch_offsets(patch_size, patch_stride)[None]
    d_world = np.einsum("oji,opj->opi", T[:, :3, :3], unproject(K[:, None], pix))
    centers = camera_centers(T)
    focal = 0.5 * (K[:, 0, 0] + K[:, 1, 1])
    return centers, d_world.astype(np.float32), np.linalg.norm(X - centers, axis=1) / focal


def voxel_sizes(reach: np.ndarray, obs_landmark: np.ndarray, n_landmarks: int, box_factor: float) -> np.ndarray:
    """Voxel side of each landmark (paper eq. 2): ``box_factor * min_i l_ij / f_i`` over its observations
    (``reach``: l / f of each observation, :func:`patch_rays`)."""
    sizes = np.full(n_landmarks, np.inf)
    np.minimum.at(sizes, obs_landmark, box_factor * reach)
    return sizes
