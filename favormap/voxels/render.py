"""Volumetric rendering of descriptors from per-landmark voxel grids (paper eqs. 3-5), batched.

A landmark owns an axis-aligned cube of side ``size`` centred on it, with R x R x R nodes on its
corners/edges (node (i, j, k) sits at ``center + size * ((i, j, k) / (R - 1) - 0.5)``). Nodes hold a
C-channel descriptor and a raw density. Rays are expressed in the cube's local frame, where the
cube is [0, 1]^3 and one unit is one voxel side; densities are per voxel side, so a grid does not
depend on the scene's scale. Along a ray, N samples between the entry and exit points are
interpolated trilinearly, and

    delta = |p_f - p_n| / N,  alpha_t = 1 - exp(-sigma_t delta),  T_t = prod_{l<t} (1 - alpha_l),
    d = sum_t T_t alpha_t d_t.

Because interpolation is linear, d = (sum_t T_t alpha_t W_t) @ G, where W_t (R^3 weights) is the
trilinear stencil of sample t and G the node descriptors: the composite stencil is computed per ray
and applied with one batched matmul per landmark group, without gathering 8 corner descriptors per
sample.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def box_intersections(origins: torch.Tensor, dirs: torch.Tensor):
    """Slab test of rays (local frame) against [0, 1]^3. Returns t_near, t_far, hit mask."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (0.0 - origins) * inv
    t1 = (1.0 - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far, t_far > t_near + 1e-9


def trilinear_stencil(points: torch.Tensor, R: int) -> torch.Tensor:
    """Dense trilinear weights (..., R^3) of local points (..., 3) in [0, 1]^3: the outer product of
    the three 1D hat functions max(0, 1 - |g - i|), which is exactly trilinear interpolation."""
    g = points.clamp(0.0, 1.0) * (R - 1)
    nodes = torch.arange(R, dtype=points.dtype, device=points.device)
    hat = (1.0 - (g[..., None] - nodes).abs()).clamp_min(0.0)  # (..., 3, R)
    w = hat[..., 0, :, None, None] * hat[..., 1, None, :, None] * hat[..., 2, None, None, :]
    return w.reshape(points.shape[:-1] + (R**3,))


def ray_stencils(origins: torch.Tensor, dirs: torch.Tensor, R: int, n_samples: int):
    """Geometry of rays (local frame; any batch shape (..., 3)). Returns the per-sample trilinear
    stencils (..., N, R^3), the sample spacing delta (...) in voxel units and the hit mask (...)."""
    dirs = F.normalize(dirs, dim=-1)
    t_near, t_far, hit = box_intersections(origins, dirs)
    span = (t_far - t_near).clamp_min(0.0)
    steps = (torch.arange(n_samples, dtype=origins.dtype, device=origins.device) + 0.5) / n_samples
    t = t_near[..., None] + span[..., None] * steps
    pts = origins[..., None, :] + t[..., None] * dirs[..., None, :]
    return trilinear_stencil(pts, R), span / n_samples, hit


def ray_corners(origins: torch.Tensor, dirs: torch.Tensor, R: int, n_samples: int):
    """Sparse form of :func:`ray_stencils`: the 8 trilinear corners of every sample. Returns flat
    node indices (..., 8, N) (long), their weights (..., 8, N), delta (...) and the hit mask (...).
    The weights are the dense stencil's non-zero entries (both are the nodes' hat functions).
    (Corner-major layout: every elementwise op runs on contiguous (..., N) blocks.)"""
    dirs = F.normalize(dirs, dim=-1)
    t_near, t_far, hit = box_intersections(origins, dirs)
    span = (t_far - t_near).clamp_min(0.0)
    steps = (torch.arange(n_samples, dtype=origins.dtype, device=origins.device) + 0.5) / n_samples
    t = t_near[..., None] + span[..., None] * steps  # (..., N)
    idx0, h = None, []
    for ax in range(3):
        g = (origins[..., ax, None] + t * dirs[..., ax, None]).clamp(0.0, 1.0) * (R - 1)
        i0 = g.floor().clamp(0, R - 2)
        f = g - i0
        h.append((1.0 - f, f))
        i0 = i0.long()
        idx0 = i0 if idx0 is None else idx0 * R + i0
    corners = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    idx = torch.stack([idx0 + (a * R * R + b * R + c) for a, b, c in corners], -2)
    hxy = [[h[0][a] * h[1][b] for b in (0, 1)] for a in (0, 1)]
    w = torch.stack([hxy[a][b] * h[2][c] for a, b, c in corners], -2)
    return idx, w, span / n_samples, hit


def render_sparse(descriptors: torch.Tensor, density_raw: torch.Tensor, idx, w, delta, hit):
    """:func:`render` with the sparse stencils of :func:`ray_corners`: rays grouped by landmark,
    idx / w (G, K, 8, N); descriptors (G, R^3, C), density_raw (G, R^3). Returns (G, K, C) and the
    accumulated opacity (G, K)."""
    G, K, _, N = idx.shape
    R3 = density_raw.shape[1]
    raw = (torch.gather(density_raw, 1, idx.reshape(G, -1)).view(G, K, 8, N) * w).sum(-2)
    sigma = F.softplus(raw)
    alpha = 1.0 - torch.exp(-sigma * delta[..., None])
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1] + 1e-10], -1), -1)
    wt = trans * alpha * hit[..., None]  # (G, K, N)
    # composite stencil (G, K, R^3): scatter the per-sample corner weights
    src = (wt[..., None, :] * w).view(G, K, 8 * N)
    a = torch.zeros(G, K, R3, dtype=w.dtype, device=w.device).scatter_add(2, idx.view(G, K, 8 * N), src)
    return torch.bmm(a, descriptors), wt.sum(-1)


def composite(stencils: torch.Tensor, delta: torch.Tensor, density_raw: torch.Tensor):
    """Composite stencil (..., R^3) and accumulated opacity (...) of rays.

    stencils: (G, K, N, R^3); delta: (G, K); density_raw: (G, R^3) for G landmark groups."""
    raw = torch.einsum("gknr,gr->gkn", stencils, density_raw)
    sigma = F.softplus(raw)
    alpha = 1.0 - torch.exp(-sigma * delta[..., None])
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1] + 1e-10], -1), -1)
    w = trans * alpha
    return torch.einsum("gkn,gknr->gkr", w, stencils), w.sum(-1)


def render(descriptors: torch.Tensor, density_raw: torch.Tensor, stencils, delta, hit):
    """Descriptors (G, K, C) of rays grouped by landmark. descriptors: (G, R^3, C)."""
    a, opacity = composite(stencils, delta, density_raw)
    a = a * hit[..., None]
    return torch.bmm(a, descriptors), opacity * hit


def to_local(points_world: torch.Tensor, centers: torch.Tensor, sizes: torch.Tensor) -> torch.Tensor:
    """World points (G, ..., 3) -> local cube coordinates; centers (G, 3), sizes (G,)."""
    shape = (-1,) + (1,) * (points_world.dim() - 2) + (3,)
    return (points_world - centers.view(shape)) / sizes.view(shape[:-1] + (1,)) + 0.5


def render_from_camera(
    descriptors, density_raw, centers, sizes, camera_center, n_samples: int = 16, normalize: bool = True
):
    """Render each landmark's descriptor along the ray from ``camera_center`` through its centre
    (paper sec. 3.3, localization). descriptors (L, R^3, C), density_raw (L, R^3), centers (L, 3),
    sizes (L,), camera_center (3,). Returns (L, C)."""
    R = round(descriptors.shape[1] ** (1 / 3))
    cam = camera_center.to(centers.dtype).expand_as(centers)
    origins = to_local(cam[:, None, :], centers, sizes)  # (L,1,3)
    dirs = (centers - cam)[:, None, :]
    st, delta, hit = ray_stencils(origins, dirs, R, n_samples)
    d, _ = render(descriptors, density_raw, st, delta, hit)
    d = d[:, 0]
    return F.normalize(d, dim=-1) if normalize else d
