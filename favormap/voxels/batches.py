"""Voxel training in batches of landmarks, each batch one task on an executor (seeded by its index, so the
map does not depend on who runs it)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from ..executor import Executor, LocalExecutor
from .config import TrainingRays, VoxelConfig, VoxelGrids
from .train import train_voxels


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
        None if rays.init_descriptors is None else rays.init_descriptors[lo:hi],
        None if rays.init_density is None else rays.init_density[lo:hi],
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
