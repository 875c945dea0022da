"""The training's figures of merit: each landmark's PSNR (MAX = 2) and mean cosine similarity of its
rendered training patches against the extracted ones (:func:`evaluate`), and the rendered patches
themselves (:func:`render_training_rays`)."""

from __future__ import annotations

import numpy as np
import torch

from .config import TrainingRays, VoxelConfig
from .losses import descriptor_losses
from .render import composite, ray_stencils, render, to_local


def fit_quality(data: TrainingRays, desc: torch.Tensor, stencils: list[tuple[slice, torch.Tensor]]):
    """:func:`evaluate` of the closed form's solution from the composite stencils its fit made
    (the densities are fixed, so they are the rendering's): the same figures without tracing every
    ray again (that was 43 % of the fox's closed-form training on two cores)."""
    L, O, C = len(data.centers), len(data.obs_landmark), desc.shape[-1]
    se, cos = torch.zeros(O), torch.zeros(O)
    obs_lm = torch.as_tensor(data.obs_landmark, device=desc.device).long()
    for sl, a in stencils:
        tgt = torch.as_tensor(data.targets[sl], dtype=torch.float32, device=desc.device)
        s_, c_ = descriptor_losses(a, desc[obs_lm[sl]], [tgt], (tgt * tgt).sum(-1))
        se[sl], cos[sl] = (s_.mean(-1) / C).cpu(), c_.mean(-1).cpu()
    return _per_landmark(data, se, cos, L)


def _per_landmark(data: TrainingRays, se: torch.Tensor, cos: torch.Tensor, L: int):
    """Per-landmark PSNR (MAX = 2) and mean cosine from per-observation squared errors and cosines."""
    lm = torch.as_tensor(data.obs_landmark).long()
    n = torch.bincount(lm, minlength=L).clamp_min(1).float()
    mse = torch.zeros(L).index_add_(0, lm, se) / n
    cs = torch.zeros(L).index_add_(0, lm, cos) / n
    psnr = 10 * torch.log10(4.0 / mse.clamp_min(1e-12))
    return psnr.numpy().astype(np.float32), cs.numpy().astype(np.float32)


@torch.no_grad()
def _training_ray_chunks(
    data: TrainingRays, desc: torch.Tensor, obs_index: np.ndarray, samples: int, chunk: int = 2048
):
    """Per chunk of observations: (positions in ``obs_index``, their landmarks, stencil geometry of
    their S*S patch rays as :func:`ray_stencils` returns it)."""
    dev = desc.device
    R = round(desc.shape[1] ** (1 / 3))
    for s in range(0, len(obs_index), chunk):
        sel = obs_index[s : s + chunk]
        lm = torch.as_tensor(data.obs_landmark[sel], device=dev).long()
        c = torch.as_tensor(data.centers[data.obs_landmark[sel]], dtype=torch.float32, device=dev)
        sz = torch.as_tensor(data.sizes[data.obs_landmark[sel]], dtype=torch.float32, device=dev)
        o = to_local(torch.as_tensor(data.obs_origin[sel], dtype=torch.float32, device=dev)[:, None, :], c, sz)
        d = torch.as_tensor(data.ray_dirs[sel], dtype=torch.float32, device=dev)
        yield slice(s, s + len(sel)), lm, ray_stencils(o.expand(-1, d.shape[1], -1), d, R, samples)


@torch.no_grad()
def render_training_rays(
    data: TrainingRays, desc: torch.Tensor, dens: torch.Tensor, cfg: VoxelConfig, obs_index: np.ndarray | None = None
):
    """Rendered descriptors (O', S*S, C) of the training patches (all or ``obs_index``)."""
    idx = np.arange(len(data.obs_landmark)) if obs_index is None else np.asarray(obs_index)
    out = torch.zeros(len(idx), data.ray_dirs.shape[1], desc.shape[-1])
    for sl, lm, geom in _training_ray_chunks(data, desc, idx, cfg.samples):
        out[sl] = render(desc[lm], dens[lm], *geom)[0].cpu()
    return out


@torch.no_grad()
def evaluate(data: TrainingRays, desc, dens, cfg: VoxelConfig):
    """Per-landmark training PSNR (MAX = 2) and mean cosine similarity of the rendered patches."""
    L, O, C = len(data.centers), len(data.obs_landmark), desc.shape[-1]
    se, cos = torch.zeros(O), torch.zeros(O)
    for sl, lm, (st, delta, hit) in _training_ray_chunks(data, desc, np.arange(O), cfg.samples):
        a, _ = composite(st, delta, dens[lm], hit)
        tgt = torch.as_tensor(data.targets[sl], dtype=torch.float32, device=desc.device)
        s_, c_ = descriptor_losses(a, desc[lm], [tgt], (tgt * tgt).sum(-1))
        se[sl], cos[sl] = (s_.mean(-1) / C).cpu(), c_.mean(-1).cpu()  # per observation (se per element)
    return _per_landmark(data, se, cos, L)
