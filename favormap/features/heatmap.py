"""Heat-map helpers shared by the learned (torch) extractors, XFeat, DISK and ALIKED.

Kept out of :mod:`favormap.features.base` so that the registry and SIFT never import torch."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def subpixel_offsets(heat: torch.Tensor, kpts: torch.Tensor) -> torch.Tensor:
    """Sub-pixel refinement of heatmap maxima: a 1D parabola through the peak and its two
    neighbours along x and along y (offsets clamped to half a pixel). ``kpts`` (N, 2) are integer
    (x, y) positions in the heatmap's pixels; returns (N, 2) offsets to add to them."""
    H, W = heat.shape
    x = kpts[:, 0].long().clamp(1, W - 2)
    y = kpts[:, 1].long().clamp(1, H - 2)
    c = heat[y, x]
    off = []
    for lo, hi in ((heat[y, x - 1], heat[y, x + 1]), (heat[y - 1, x], heat[y + 1, x])):
        den = 2 * c - lo - hi
        d = torch.where(den > 1e-12, 0.5 * (hi - lo) / den.clamp_min(1e-12), torch.zeros_like(c))
        off.append(d.clamp(-0.5, 0.5))
    inside = ((kpts[:, 0] >= 1) & (kpts[:, 0] <= W - 2) & (kpts[:, 1] >= 1) & (kpts[:, 1] <= H - 2)).float()
    return torch.stack(off, 1) * inside[:, None]


def local_maxima(heat: torch.Tensor, radius: int, threshold: float, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) integer (x, y) maxima of ``heat`` (H, W), strongest first, and their scores: positions equal to
    the maximum of their (2 radius + 1)^2 window, above ``threshold``, at least ``radius`` from the border;
    the ``k`` strongest."""
    r = int(radius)
    h, w = heat.shape
    peak = F.max_pool2d(heat[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]
    mask = (heat == peak) & (heat > threshold)
    mask[:r], mask[h - r :], mask[:, :r], mask[:, w - r :] = False, False, False, False
    yx = mask.nonzero()
    scores = heat[yx[:, 0], yx[:, 1]]
    top = torch.argsort(-scores)[:k]
    return yx[top].flip(1), scores[top]
