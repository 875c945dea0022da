"""Training all landmark voxel grids at once (paper sec. 3.3 and supplement "Training and Losses").

Every landmark is an independent little model, so they are stacked into tensors of shape
(L, R^3, C) and optimised together: each iteration draws ``rays_per_landmark`` patch rays for every
landmark and takes one Adam step on all of them. Losses: squared L2 + cosine on the rendered
descriptor, total variation on both grids for the last quarter of the iterations and an entropy
regulariser on the accumulated opacity. As in DVGO/FaVoR, the learning rate of a node is scaled by
how many training views see it (relative to the landmark's best-seen node).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from .render import render, ray_stencils, to_local


@dataclass
class VoxelConfig:
    resolution: int = 3  # R
    patch_size: int = 7  # S
    samples: int = 12  # N samples per ray
    iterations: int = 200
    rays_per_landmark: int = 32
    lr_descriptors: float = 0.01
    lr_density: float = 0.1
    tv_weight: float = 1e-3
    entropy_weight: float = 1e-3
    density_init: float = 1.0  # initial sigma per voxel side
    seed: int = 0
    device: str = "cpu"


@dataclass
class TrainingRays:
    """Training data: every observation contributes S*S rays (one per patch pixel)."""

    centers: np.ndarray  # (L, 3) landmark positions (world)
    sizes: np.ndarray  # (L,) voxel side lengths (world)
    obs_landmark: np.ndarray  # (O,) landmark of each observation, sorted
    obs_origin: np.ndarray  # (O, 3) camera centre (world)
    ray_dirs: np.ndarray  # (O, S*S, 3) world directions of the patch pixels
    targets: np.ndarray  # (O, S*S, C) descriptors extracted at the patch pixels (unit norm)


@dataclass
class VoxelGrids:
    """Trained voxels: stage boundary between voxel training and the map file."""

    descriptors: torch.Tensor  # (L, R^3, C), node order (x, y, z) row-major
    density: torch.Tensor  # (L, R^3) raw density (softplus -> sigma per voxel side)
    psnr: np.ndarray  # (L,) training PSNR, MAX = 2
    cosine: np.ndarray  # (L,) mean cosine similarity of rendered vs extracted training descriptors
    history: list = field(default_factory=list)  # (iteration, loss, psnr) samples

    @property
    def resolution(self) -> int:
        return round(self.descriptors.shape[1] ** (1 / 3))


class _BatchedAdam:
    """Adam on stacked per-landmark tensors with a per-node learning-rate factor."""

    def __init__(self, params, lrs, factors, betas=(0.9, 0.99), eps=1e-15):
        self.params, self.lrs, self.factors = params, lrs, factors
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]
        self.b1, self.b2, self.eps, self.t = betas[0], betas[1], eps, 0

    @torch.no_grad()
    def step(self, lr_scale=1.0):
        self.t += 1
        c1 = 1 - self.b1 ** self.t
        c2 = 1 - self.b2 ** self.t
        for p, m, v, lr, f in zip(self.params, self.m, self.v, self.lrs, self.factors):
            g = p.grad
            m.mul_(self.b1).add_(g, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
            upd = (m / c1) / ((v / c2).sqrt() + self.eps)
            p.sub_(lr * lr_scale * (f.view(f.shape + (1,) * (p.dim() - f.dim())) * upd))
            p.grad = None


def _tv(x: torch.Tensor, R: int) -> torch.Tensor:
    g = x.view(x.shape[0], R, R, R, -1)
    return ((g[:, 1:] - g[:, :-1]) ** 2).mean() + ((g[:, :, 1:] - g[:, :, :-1]) ** 2).mean() + ((g[:, :, :, 1:] - g[:, :, :, :-1]) ** 2).mean()


def _visibility(data, origins_l, dirs_all, R, cfg, device) -> torch.Tensor:
    """(L, R^3) number of training observations whose patch rays touch each node."""
    L = len(data.centers)
    counts = torch.zeros(L, R ** 3, device=device)
    O = len(data.obs_landmark)
    chunk = max(1, 60000 // dirs_all.shape[1])
    lm = torch.as_tensor(data.obs_landmark, device=device).long()
    for s in range(0, O, chunk):
        sl = slice(s, min(O, s + chunk))
        st, delta, hit = ray_stencils(origins_l[sl][:, None, :].expand(-1, dirs_all.shape[1], -1), dirs_all[sl], R, cfg.samples)
        touched = ((st.sum(-2) > 0) & hit[..., None]).any(1).float()  # (chunk, R^3)
        counts.index_add_(0, lm[sl], touched)
    return counts


def train_voxels(data: TrainingRays, cfg: VoxelConfig, progress: Callable[[int, float, float], None] | None = None) -> VoxelGrids:
    dev = torch.device(cfg.device)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
    R, C = cfg.resolution, data.targets.shape[-1]
    L, P = len(data.centers), data.ray_dirs.shape[1]
    f32 = dict(dtype=torch.float32, device=dev)
    centers = torch.as_tensor(data.centers, **f32)
    sizes = torch.as_tensor(data.sizes, **f32)
    obs_lm = torch.as_tensor(data.obs_landmark, device=dev).long()
    # ray origins in each landmark's local frame; directions scaled to local units
    origins_l = (torch.as_tensor(data.obs_origin, **f32) - centers[obs_lm]) / sizes[obs_lm, None] + 0.5
    dirs_all = torch.as_tensor(data.ray_dirs, **f32)
    targets = torch.as_tensor(data.targets, **f32)

    counts = torch.bincount(obs_lm, minlength=L)
    first = torch.cumsum(counts, 0) - counts

    # init: every node holds the track's mean descriptor; uniform density
    mean_desc = torch.zeros(L, C, **f32).index_add_(0, obs_lm, targets.mean(1))
    mean_desc = F.normalize(mean_desc, dim=-1)
    desc = mean_desc[:, None, :].repeat(1, R ** 3, 1).contiguous().requires_grad_(True)
    raw0 = math.log(math.expm1(cfg.density_init))
    dens = torch.full((L, R ** 3), raw0, **f32).requires_grad_(True)

    vis = _visibility(data, origins_l, dirs_all, R, cfg, dev)
    factor = vis / vis.amax(1, keepdim=True).clamp_min(1.0)
    opt = _BatchedAdam([desc, dens], [cfg.lr_descriptors, cfg.lr_density], [factor, factor])

    K = cfg.rays_per_landmark
    history = []
    tv_start = int(cfg.iterations * 0.75)
    for it in range(cfg.iterations):
        r = torch.rand(L, K, generator=gen).to(dev)
        obs = first[:, None] + torch.minimum((r * counts[:, None]).long(), counts[:, None] - 1)  # (L,K) observations
        pix = torch.randint(0, P, (L, K), generator=gen).to(dev)
        o = origins_l[obs]  # (L,K,3)
        d = dirs_all[obs, pix]
        tgt = targets[obs, pix]
        st, delta, hit = ray_stencils(o, d, R, cfg.samples)
        pred, opacity = render(desc, dens, st, delta, hit)
        m = hit.float()
        nm = m.sum().clamp_min(1.0)
        se = ((pred - tgt) ** 2).sum(-1)
        cos = F.cosine_similarity(pred, tgt, dim=-1, eps=1e-8)
        loss = ((se + (1 - cos)) * m).sum() / nm
        op = opacity.clamp(1e-6, 1 - 1e-6)
        loss = loss + cfg.entropy_weight * ((-(op * op.log() + (1 - op) * (1 - op).log())) * m).sum() / nm
        if it >= tv_start:
            loss = loss + cfg.tv_weight * (_tv(desc, R) + _tv(dens[..., None], R))
        loss.backward()
        lr_scale = 0.1 ** (it / max(1, cfg.iterations))  # exponential decay to 0.1x
        opt.step(lr_scale)
        if it % 25 == 0 or it == cfg.iterations - 1:
            with torch.no_grad():
                mse = ((se * m).sum() / nm / C).item()
            history.append((it, float(loss.item()), 10 * math.log10(4.0 / max(mse, 1e-12))))
            if progress:
                progress(it, history[-1][1], history[-1][2])

    desc = desc.detach()
    dens = dens.detach()
    psnr, cosine = evaluate(data, desc, dens, cfg)
    return VoxelGrids(desc, dens, psnr, cosine, history)


@torch.no_grad()
def render_training_rays(data: TrainingRays, desc: torch.Tensor, dens: torch.Tensor, cfg: VoxelConfig, obs_index: np.ndarray | None = None):
    """Rendered descriptors (O', S*S, C) of the training patches (all or ``obs_index``)."""
    dev = desc.device
    R = round(desc.shape[1] ** (1 / 3))
    idx = np.arange(len(data.obs_landmark)) if obs_index is None else np.asarray(obs_index)
    out = torch.zeros(len(idx), data.ray_dirs.shape[1], desc.shape[-1])
    chunk = 2048
    for s in range(0, len(idx), chunk):
        sel = idx[s : s + chunk]
        lm = torch.as_tensor(data.obs_landmark[sel], device=dev).long()
        c = torch.as_tensor(data.centers[data.obs_landmark[sel]], dtype=torch.float32, device=dev)
        sz = torch.as_tensor(data.sizes[data.obs_landmark[sel]], dtype=torch.float32, device=dev)
        o = to_local(torch.as_tensor(data.obs_origin[sel], dtype=torch.float32, device=dev)[:, None, :], c, sz)
        d = torch.as_tensor(data.ray_dirs[sel], dtype=torch.float32, device=dev)
        st, delta, hit = ray_stencils(o.expand(-1, d.shape[1], -1), d, R, cfg.samples)
        pred, _ = render(desc[lm], dens[lm], st, delta, hit)
        out[s : s + len(sel)] = pred.cpu()
    return out


def evaluate(data: TrainingRays, desc, dens, cfg: VoxelConfig):
    """Per-landmark training PSNR (MAX = 2) and mean cosine similarity."""
    pred = render_training_rays(data, desc, dens, cfg)
    tgt = torch.as_tensor(data.targets, dtype=torch.float32)
    L = len(data.centers)
    lm = torch.as_tensor(data.obs_landmark).long()
    se = ((pred - tgt) ** 2).mean(-1).mean(-1)  # per observation, per element
    cos = F.cosine_similarity(pred, tgt, dim=-1).mean(-1)
    n = torch.bincount(lm, minlength=L).clamp_min(1).float()
    mse = torch.zeros(L).index_add_(0, lm, se) / n
    cs = torch.zeros(L).index_add_(0, lm, cos) / n
    psnr = 10 * torch.log10(4.0 / mse.clamp_min(1e-12))
    return psnr.numpy().astype(np.float32), cs.numpy().astype(np.float32)
