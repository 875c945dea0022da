"""The losses of the voxel training: each ray's rendered descriptor against its target (squared L2
distance and cosine) and the entropy of its accumulated opacity, weighted as :class:`VoxelConfig` says."""

from __future__ import annotations

import torch

from .config import VoxelConfig


def descriptor_losses(a: torch.Tensor, desc: torch.Tensor, targets: list[torch.Tensor], target_sq: torch.Tensor):
    """Squared L2 distance and cosine similarity (G, K) of the rendered descriptors a @ desc to the
    targets, without forming the rendered descriptors: with p = a D and D the (R^3, C) node
    descriptors, p.t = a (D t) and |p|^2 = a (D D^T) a. The per-ray tensors are (G, K, R^3)
    instead of (G, K, C), which takes the C-wide elementwise work of the loss (and of its
    gradient) out of the training loop. ``targets``: (G, K_i, C) blocks, concatenated along K."""
    dt = torch.cat([torch.bmm(desc, t.transpose(1, 2)) for t in targets], 2)  # (G, R^3, K)
    dot = (a * dt.transpose(1, 2)).sum(-1)
    gram = torch.bmm(desc, desc.transpose(1, 2))  # (G, R^3, R^3)
    p_sq = (torch.bmm(a, gram) * a).sum(-1)
    se = (p_sq - 2 * dot + target_sq).clamp_min(0.0)
    cos = dot / (p_sq.clamp_min(1e-16) * target_sq.clamp_min(1e-16)).sqrt().clamp_min(1e-8)
    return se, cos


def ray_loss(
    cfg: VoxelConfig,
    se: torch.Tensor,
    cos: torch.Tensor,
    opacity: torch.Tensor,
    weight: torch.Tensor,
    norm: float,
) -> torch.Tensor:
    """The training loss of a group of rays (G, K): ``cfg``'s weighted sum of the squared error, the cosine
    distance and the entropy of the accumulated opacity, each ray weighted by ``weight``, over ``norm``."""
    op = opacity.clamp(1e-6, 1 - 1e-6)
    ent = -(op * op.log() + (1 - op) * (1 - op).log())
    return ((cfg.mse_weight * se + cfg.cosine_weight * (1 - cos) + cfg.entropy_weight * ent) * weight).sum() / norm
