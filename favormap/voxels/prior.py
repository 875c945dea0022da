"""The view-extrapolation prior of the voxel training: virtual centre rays from directions turned away
from each landmark's training views, with targets from the nearest views' descriptors (both solvers of
:mod:`favormap.voxels.train` train on them)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..features.base import ExtractorPolicy
from .config import TrainingRays, VoxelConfig


@dataclass
class PriorRays:
    """V virtual centre rays per landmark, in the landmark's local frame (its box is the unit cube)."""

    origins: torch.Tensor  # (L, V, 3)
    dirs: torch.Tensor  # (L, V, 3)
    targets: torch.Tensor  # (L, V, C)


def prior_bank(
    data: TrainingRays, cfg: VoxelConfig, centers, sizes, targets, mean_desc, counts, first, gen
) -> PriorRays:
    """Virtual centre rays per landmark (L, V): local origins, local directions and targets.

    A virtual direction is a training view's direction turned by a uniform random angle in
    [0, prior_spread_deg] about a random axis (the ray starts at that view's distance and goes
    through the landmark, like the rays the localizer renders). Its target blends the centre
    descriptors of the landmark's training views with weights exp(-(a - a_min)^2 / 2 b^2), a the
    angles to them and b = prior_kernel_deg, so that far from the training views it tends to the
    nearest view's descriptor (flat extrapolation) instead of whatever the grid's interpolation
    continues to; with prior_mean_deg = tau > 0 that blend is mixed with the mean descriptor,
    weight exp(-a_min / tau) for the views. (prior_mean_deg None here: ExtractorPolicy's default.)"""
    dev = centers.device
    L, V, P = len(centers), cfg.prior_bank, targets.shape[1]
    origins = torch.as_tensor(data.obs_origin, dtype=torch.float32, device=dev)
    base = torch.minimum((gen.rand(V).to(dev) * counts[:, None]).long(), counts[:, None] - 1)
    g = gen.randn(V, 3).to(dev)
    theta = gen.rand(V, 1).to(dev) * math.radians(cfg.prior_spread_deg)
    out_o, out_d, out_t = [], [], []
    chunk = max(1, (1 << 22) // max(1, V * int(counts.max())))
    for s in range(0, L, chunk):
        ls = slice(s, min(L, s + chunk))
        n_max = int(counts[ls].max())
        ar = torch.arange(n_max, device=dev)
        valid = ar[None] < counts[ls, None]
        idx = torch.where(valid, first[ls, None] + ar[None], first[ls, None])  # (l, n_max) observations
        vec = origins[idx] - centers[ls, None]
        dist = vec.norm(dim=-1)
        U = vec / dist[..., None].clamp_min(1e-12)  # landmark -> camera, unit
        D = targets[idx, P // 2].to(torch.float32)  # (l, n_max, C) centre descriptors
        u0 = torch.gather(U, 1, base[ls, :, None].expand(-1, -1, 3))
        t = F.normalize(g[ls] - (g[ls] * u0).sum(-1, keepdim=True) * u0, dim=-1)
        v = torch.cos(theta[ls]) * u0 + torch.sin(theta[ls]) * t
        ang = torch.rad2deg(torch.acos(torch.einsum("lvd,lod->lvo", v, U).clamp(-1, 1)))
        ang = torch.where(valid[:, None, :], ang, torch.full_like(ang, 1e4))
        w = (
            torch.exp(-0.5 * ((ang - ang.amin(-1, keepdim=True)) / max(cfg.prior_kernel_deg, 1e-3)) ** 2)
            * valid[:, None, :]
        )
        tgt = F.normalize(torch.bmm(w, D), dim=-1)
        tau = cfg.prior_mean_deg if cfg.prior_mean_deg is not None else ExtractorPolicy.view_prior_deg
        if tau > 0:
            beta = torch.exp(-ang.amin(-1, keepdim=True) / tau)  # (l, V, 1)
            tgt = F.normalize(beta * tgt + (1 - beta) * mean_desc[ls, None, :], dim=-1)
        out_t.append(tgt)
        r = torch.gather(dist, 1, base[ls])  # distance of the training view the direction came from
        out_o.append(v * (r / sizes[ls, None])[..., None] + 0.5)
        out_d.append(-v)
    return PriorRays(torch.cat(out_o), torch.cat(out_d), torch.cat(out_t))
