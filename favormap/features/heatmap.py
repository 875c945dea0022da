"""Heat-map helpers shared by the learned (torch) extractors, XFeat, DISK, ALIKED and ALIKE.

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


def local_maxima(
    heat: torch.Tensor, radius: int, threshold: float, k: int, rounds: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) integer (x, y) maxima of ``heat`` (H, W), strongest first, and their scores: positions equal to
    the maximum of their (2 radius + 1)^2 window, above ``threshold``, at least ``radius`` from the border;
    the ``k`` strongest. ``rounds`` > 0 adds, that many times, the maxima of what is left once every
    window of a maximum found so far is cleared (SuperPoint's NMS, which ALIKE publishes with 2 rounds)."""
    r = int(radius)
    h, w = heat.shape

    def pool(x):
        return F.max_pool2d(x[None, None], 2 * r + 1, stride=1, padding=r)[0, 0]

    found = heat == pool(heat)
    for _ in range(int(rounds)):
        cleared = pool(found.float()) > 0
        rest = torch.where(cleared, torch.zeros_like(heat), heat)
        found = found | ((rest == pool(rest)) & ~cleared)
    mask = found & (heat > threshold)
    mask[:r], mask[h - r :], mask[:, :r], mask[:, w - r :] = False, False, False, False
    yx = mask.nonzero()
    scores = heat[yx[:, 0], yx[:, 1]]
    top = torch.argsort(-scores)[:k]
    return yx[top].flip(1), scores[top]


def soft_argmax(heat: torch.Tensor, kpts: torch.Tensor, radius: int, temperature: float = 0.1) -> torch.Tensor:
    """Sub-pixel refinement of heatmap maxima by the soft-argmax of their (2 radius + 1)^2 window (the one
    ALIKE and ALIKED publish): the window's offsets weighed by exp((heat - peak) / temperature). ``kpts``
    (N, 2) are integer (x, y) positions at least ``radius`` from the border (local_maxima's); returns
    their (N, 2) float positions."""
    r = int(radius)
    k = 2 * r + 1
    yx = kpts.long().flip(1)
    d = torch.arange(-r, r + 1, device=heat.device)
    win = heat[yx[:, 0, None, None] + d.view(1, k, 1), yx[:, 1, None, None] + d.view(1, 1, k)].reshape(len(yx), k * k)
    e = ((win - win.max(1, keepdim=True).values) / temperature).exp()
    gy, gx = torch.meshgrid(d.float(), d.float(), indexing="ij")
    dx = (e * gx.reshape(1, -1)).sum(1) / e.sum(1)
    dy = (e * gy.reshape(1, -1)).sum(1) / e.sum(1)
    return torch.stack([yx[:, 1] + dx, yx[:, 0] + dy], 1).float()
