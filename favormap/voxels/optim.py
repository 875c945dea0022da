"""The optimiser of the voxel training (:func:`favormap.voxels.train.train_voxels`): Adam on the stacked
per-landmark grids with a per-node learning-rate factor (how many training views see the node), and the
total-variation term's gradient in closed form."""

from __future__ import annotations

import torch

from .render import ray_stencils


class BatchedAdam:
    """Adam on stacked per-landmark tensors with a per-node learning-rate factor."""

    def __init__(self, params, lrs, factors, betas=(0.9, 0.99), eps=1e-15):
        self.params, self.lrs, self.factors = params, lrs, factors
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]
        self.buf = [torch.empty_like(p) for p in params]
        self.b1, self.b2, self.eps, self.t = betas[0], betas[1], eps, 0

    @torch.no_grad()
    def step(self, lr_scale=1.0):
        self.t += 1
        c1 = 1 - self.b1**self.t
        c2 = 1 - self.b2**self.t
        for p, m, v, lr, f, buf in zip(self.params, self.m, self.v, self.lrs, self.factors, self.buf):
            g = p.grad
            m.mul_(self.b1).add_(g, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
            # p -= lr f (m / c1) / (sqrt(v / c2) + eps), in place in one buffer per parameter
            torch.div(v, c2, out=buf).sqrt_().add_(self.eps)
            torch.div(m, buf, out=buf).mul_(f.view(f.shape + (1,) * (p.dim() - f.dim())))
            p.sub_(buf, alpha=lr * lr_scale / c1)
            p.grad = None


class TVGradient:
    """The total-variation term of the training, ``tv_weight * (TV(desc) + TV(density))``, added to
    the parameters' gradients in closed form. TV of a stack of grids (L, R^3, C) is the mean squared
    difference of neighbouring nodes along each axis, summed over the axes: a quadratic form x^T M x
    over the node axis, M the grid's graph Laplacian (the sum over the three axes of D^T D, D the
    differences of neighbouring nodes) over the number of squared differences each mean averages
    ((R - 1) R^2 per axis, times the landmarks and channels). So its gradient is 2 M x, one
    (R^3 x R^3) matrix product (tests/test_core.py checks it against autograd through the slices,
    which took ~0.1 s per iteration on two cores for the fox's 3,000 landmarks)."""

    def __init__(self, R: int, L: int, C: int, device):
        lap = grid_laplacian(R, dtype=torch.float32, device=device) / ((R - 1) * R * R * L)
        self.m_desc, self.m_dens = lap / C, lap

    @torch.no_grad()
    def add_to(self, desc: torch.Tensor, dens: torch.Tensor, weight: float) -> float:
        """Adds ``weight`` times the term's gradient to ``desc.grad`` and ``dens.grad``; returns its value."""
        y = torch.matmul(self.m_desc, desc)  # (L, R^3, C)
        z = dens @ self.m_dens  # (L, R^3); M is symmetric
        for p in (desc, dens):
            if p.grad is None:  # no rendering loss reached it this step
                p.grad = torch.zeros_like(p)
        desc.grad.add_(y, alpha=2 * weight)
        dens.grad.add_(z, alpha=2 * weight)
        return weight * float((desc * y).sum() + (dens * z).sum())


def node_visibility(data, origins_l, dirs_all, R, cfg, device) -> torch.Tensor:
    """(L, R^3) number of training observations whose patch rays touch each node."""
    L = len(data.centers)
    counts = torch.zeros(L, R**3, device=device)
    O = len(data.obs_landmark)
    chunk = max(1, 60000 // dirs_all.shape[1])
    lm = torch.as_tensor(data.obs_landmark, device=device).long()
    for s in range(0, O, chunk):
        sl = slice(s, min(O, s + chunk))
        st, _, hit = ray_stencils(
            origins_l[sl][:, None, :].expand(-1, dirs_all.shape[1], -1), dirs_all[sl], R, cfg.samples
        )
        touched = ((st > 0) & hit[:, None, :, None]).flatten(2).any(-1)  # (n, R^3)
        counts.index_add_(0, lm[sl], touched.float())
    return counts


def grid_laplacian(R: int, **kw) -> torch.Tensor:
    """(R^3, R^3) graph Laplacian of the node grid: x^T Lap x = sum over neighbouring nodes of the
    squared difference (the TV term of the least-squares fit)."""
    idx = torch.arange(R**3).view(R, R, R)
    pairs = [
        torch.stack([idx.narrow(ax, 0, R - 1).reshape(-1), idx.narrow(ax, 1, R - 1).reshape(-1)], 1) for ax in range(3)
    ]
    i, j = torch.cat(pairs).T
    lap = torch.zeros(R**3, R**3, **kw)
    lap.index_put_((i, i), torch.ones(len(i), **kw), accumulate=True)
    lap.index_put_((j, j), torch.ones(len(j), **kw), accumulate=True)
    lap.index_put_((i, j), torch.full((len(i),), -1.0, **kw), accumulate=True)
    lap.index_put_((j, i), torch.full((len(i),), -1.0, **kw), accumulate=True)
    return lap
