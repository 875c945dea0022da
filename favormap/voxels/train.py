"""Training all landmark voxel grids at once (paper sec. 3.3 and supplement "Training and Losses").

(One module for both solvers, Adam and the closed form: they share the rays, the view-extrapolation prior and
the evaluation below; the settings and stage types are in :mod:`.config`.)

Every landmark is an independent little model, so they are stacked into tensors of shape
(L, R^3, C) and optimised together: each iteration draws rays for every landmark and takes one Adam
step on all of them (landmarks are processed in groups of at most ``max_batch_rays`` rays, the
gradients accumulating, so memory stays bounded). Losses: squared L2 + cosine on the rendered
descriptor, total variation on both grids for the last part of the iterations and an entropy
regulariser on the accumulated opacity. As in DVGO/FaVoR, the learning rate of a node is scaled by
how many training views see it (relative to the landmark's best-seen node).

Rays per landmark and iteration (see ``VoxelConfig``):

- ``rays_per_landmark`` real rays, a random observation each; a fraction ``centre_rays`` of them
  goes through the patch centre (the one ray the localizer renders, through the landmark), the rest
  through a random patch pixel (the paper's S x S patch rays);
- ``prior_rays`` virtual centre rays (view-extrapolation prior): from directions turned up to
  ``prior_spread_deg`` away from the training views, with the descriptor of the nearest training
  view(s) as target (mixed with the mean descriptor further away for extractors where that predicts
  better, ``prior_mean_deg``). Without them the grid continues its fit beyond the training views
  and overshoots; with them it extrapolates like the nearest view (``tools/bench_novel_view.py``
measures it; docs/implementation-notes.md).

``QUALITY_PRESETS`` / :meth:`VoxelConfig.preset`: "fast" (the dataclass's defaults: Adam, sized for a
few CPU cores), "quick" and "balanced" (closed-form descriptors: speed first, or Adam's accuracy in a
quarter of its time; "balanced" is what a SIFT build uses, ``ExtractorPolicy.training_quality``) and "reference" (the
budget of the reference implementation, 2,000 iterations x 1,024 rays and a 12 l/f box; meant for a
GPU).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..features.base import ExtractorPolicy
from .config import TrainingRays, VoxelConfig, VoxelGrids
from .render import composite, composite_uniform, ray_stencils, render, to_local


class _BatchedAdam:
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


class BlockGenerator:
    """Random numbers for consecutive blocks of landmarks (``sizes``), block k from its own CPU
    generator seeded ``seed + k``; each call returns the blocks' draws stacked along the landmark
    axis, so a block gets the same numbers whichever blocks it is trained with."""

    def __init__(self, sizes: Sequence[int], seed: int):
        self.sizes = [int(n) for n in sizes]
        self.gens = [torch.Generator(device="cpu").manual_seed(seed + k) for k in range(len(self.sizes))]

    def _cat(self, draw) -> torch.Tensor:
        parts = [draw(n, g) for n, g in zip(self.sizes, self.gens)]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def rand(self, *shape: int) -> torch.Tensor:
        """(L, *shape) uniform in [0, 1)."""
        return self._cat(lambda n, g: torch.rand(n, *shape, generator=g))

    def randn(self, *shape: int) -> torch.Tensor:
        """(L, *shape) standard normal."""
        return self._cat(lambda n, g: torch.randn(n, *shape, generator=g))

    def randint(self, high: int, *shape: int) -> torch.Tensor:
        """(L, *shape) integers in [0, high)."""
        return self._cat(lambda n, g: torch.randint(0, high, (n, *shape), generator=g))


class _TVGradient:
    """The total-variation term of the training, ``tv_weight * (TV(desc) + TV(density))``, added to
    the parameters' gradients in closed form. TV of a stack of grids (L, R^3, C) is the mean squared
    difference of neighbouring nodes along each axis, summed over the axes: a quadratic form x^T M x
    over the node axis, M the grid's graph Laplacian (the sum over the three axes of D^T D, D the
    differences of neighbouring nodes) over the number of squared differences each mean averages
    ((R - 1) R^2 per axis, times the landmarks and channels). So its gradient is 2 M x, one
    (R^3 x R^3) matrix product (tests/test_core.py checks it against autograd through the slices,
    which took ~0.1 s per iteration on two cores for the fox's 3,000 landmarks)."""

    def __init__(self, R: int, L: int, C: int, device):
        lap = _grid_laplacian(R, dtype=torch.float32, device=device) / ((R - 1) * R * R * L)
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


def _visibility(data, origins_l, dirs_all, R, cfg, device) -> torch.Tensor:
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


def _prior_bank(data: TrainingRays, cfg: VoxelConfig, centers, sizes, targets, mean_desc, counts, first, gen):
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
    return torch.cat(out_o), torch.cat(out_d), torch.cat(out_t)


def _track_means(data: TrainingRays, obs_lm: torch.Tensor, L: int, **f32) -> torch.Tensor:
    """(L, C) unit mean descriptor of each landmark's track, as the map's mean_descriptor: the mean of
    its observations' patch means (:meth:`TrainingRays.patch_means`, from before the float16 rounding)."""
    means = torch.as_tensor(data.patch_means(), **f32)
    return F.normalize(torch.zeros(L, means.shape[-1], **f32).index_add_(0, obs_lm, means), dim=-1)


def _losses(a: torch.Tensor, desc: torch.Tensor, targets: list[torch.Tensor], target_sq: torch.Tensor):
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


def train_voxels(
    data: TrainingRays,
    cfg: VoxelConfig,
    progress: Callable[[int, float, float], None] | None = None,
    device: str | torch.device = "cpu",
    seed_blocks: Sequence[int] | None = None,
) -> VoxelGrids:
    """Train every landmark's grids on ``device`` (the result stays there).

    ``seed_blocks``: sizes of consecutive blocks of the landmarks, block k drawing its random rays
    from its own generator seeded ``cfg.seed + k`` (None: one block). Training several blocks in
    one call gives what training each block alone gives (the landmarks are independent, and Adam
    does not see the loss's 1 / landmark-count scale), in fewer, larger steps: what a GPU wants."""
    if cfg.solver == "lstsq":
        return _train_lstsq(data, cfg, progress, device, seed_blocks=seed_blocks)
    if cfg.solver != "adam":
        raise ValueError(f"unknown VoxelConfig.solver {cfg.solver!r} (lstsq, adam)")
    dev = torch.device(device)
    gen = BlockGenerator(seed_blocks or [len(data.centers)], cfg.seed)
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

    target_sq = (targets * targets).sum(-1)  # (O, P) |target|^2 (1 for unit descriptors)
    counts = torch.bincount(obs_lm, minlength=L)
    first = torch.cumsum(counts, 0) - counts

    mean_desc = _track_means(data, obs_lm, L, **f32)
    # init: every node holds the mean descriptor (or zero); uniform density
    if cfg.init not in ("mean", "zero", "lstsq"):
        raise ValueError(f"unknown VoxelConfig.init {cfg.init!r} (mean, zero, lstsq)")
    if cfg.init == "lstsq":  # start from the closed-form fit at the initial densities
        fit = _train_lstsq(data, cfg, None, dev, evaluate_fit=False, seed_blocks=seed_blocks)
        desc = fit.descriptors.contiguous().requires_grad_(True)
    else:
        init = mean_desc if cfg.init == "mean" else torch.zeros_like(mean_desc)
        desc = init[:, None, :].repeat(1, R**3, 1).contiguous().requires_grad_(True)
    raw0 = math.log(math.expm1(cfg.density_init))
    dens = torch.full((L, R**3), raw0, **f32)
    if data.init_descriptors is not None:  # fine-tuning: the landmarks with grids start from them
        d0 = torch.as_tensor(np.asarray(data.init_descriptors, np.float32).reshape(L, R**3, C), device=dev)
        s0 = torch.as_tensor(np.asarray(data.init_density, np.float32).reshape(L, R**3), device=dev)
        has = torch.isfinite(d0).flatten(1).all(1) & torch.isfinite(s0).all(1)
        with torch.no_grad():
            desc[has] = d0[has]
            dens[has] = s0[has]
    dens.requires_grad_(True)

    if cfg.pervoxel_lr:
        vis = _visibility(data, origins_l, dirs_all, R, cfg, dev)
        factor = vis / vis.amax(1, keepdim=True).clamp_min(1.0)
    else:
        factor = torch.ones(L, R**3, **f32)
    opt = _BatchedAdam([desc, dens], [cfg.lr_descriptors, cfg.lr_density], [factor, factor])

    K, Kp = cfg.rays_per_landmark, cfg.prior_rays
    if Kp > 0:
        pb_o, pb_d, pb_t = _prior_bank(data, cfg, centers, sizes, targets, mean_desc, counts, first, gen)
        pb_sq = (pb_t * pb_t).sum(-1)
    ray_w = torch.cat([torch.ones(K, **f32), torch.full((Kp,), cfg.prior_weight, **f32)])
    norm = float(L * ray_w.sum())  # loss = weighted mean over all rays of all landmarks
    group = max(1, cfg.max_batch_rays // (K + Kp))
    history = []
    tv_start = int(cfg.iterations * cfg.tv_from)
    # flat row views: one index_select per gather (2-4x faster on a CPU than advanced indexing or
    # torch.gather with an expanded index; the same values)
    dirs_flat, targets_flat, tsq_flat = dirs_all.view(-1, 3), targets.view(-1, C), target_sq.view(-1)
    if Kp > 0:
        pb_o, pb_d, pb_t, pb_sq = pb_o.view(-1, 3), pb_d.view(-1, 3), pb_t.view(-1, C), pb_sq.view(-1)
    tv_grad = _TVGradient(R, L, C, dev) if cfg.tv_weight > 0 else None
    for it in range(cfg.iterations):
        r = gen.rand(K).to(dev)
        obs = first[:, None] + torch.minimum((r * counts[:, None]).long(), counts[:, None] - 1)  # (L,K) observations
        pix = gen.randint(P, K)
        if cfg.centre_rays > 0:
            pix = torch.where(gen.rand(K) < cfg.centre_rays, P // 2, pix)
        ray = obs * P + pix.to(dev)  # (L,K) rows of the flat (O*P) patch rays
        sel = gen.randint(cfg.prior_bank, Kp).to(dev) if Kp > 0 else None
        total, se_real = 0.0, 0.0
        for g0 in range(0, L, group):
            gs = slice(g0, min(L, g0 + group))
            G = gs.stop - gs.start
            rg = ray[gs].reshape(-1)
            o = origins_l.index_select(0, obs[gs].reshape(-1)).view(G, K, 3)
            d = dirs_flat.index_select(0, rg).view(G, K, 3)
            tgts = [targets_flat.index_select(0, rg).view(G, K, C)]
            tn2 = tsq_flat.index_select(0, rg).view(G, K)
            if Kp > 0:
                pr = (torch.arange(g0, gs.stop, device=dev)[:, None] * cfg.prior_bank + sel[gs]).reshape(-1)
                o = torch.cat([o, pb_o.index_select(0, pr).view(G, Kp, 3)], 1)
                d = torch.cat([d, pb_d.index_select(0, pr).view(G, Kp, 3)], 1)
                tgts.append(pb_t.index_select(0, pr).view(G, Kp, C))
                tn2 = torch.cat([tn2, pb_sq.index_select(0, pr).view(G, Kp)], 1)
            st, delta, hit = ray_stencils(o, d, R, cfg.samples)
            a, opacity = composite(st, delta, dens[gs], hit)  # (G,K,R^3): pred = a @ desc
            se, cos = _losses(a, desc[gs], tgts, tn2)
            m = hit.float() * ray_w
            op = opacity.clamp(1e-6, 1 - 1e-6)
            ent = -(op * op.log() + (1 - op) * (1 - op).log())
            loss = ((cfg.mse_weight * se + cfg.cosine_weight * (1 - cos) + cfg.entropy_weight * ent) * m).sum() / norm
            loss.backward()
            total += float(loss.detach())
            se_real += float(se[:, :K].detach().sum())
        if it >= tv_start and tv_grad is not None:
            total += tv_grad.add_to(desc, dens, cfg.tv_weight)
        lr_scale = cfg.lr_final ** (it / max(1, cfg.iterations - 1))  # exponential decay to lr_final
        opt.step(lr_scale)
        if it % 25 == 0 or it == cfg.iterations - 1:
            mse = se_real / (L * K * C)  # real rays only
            history.append((it, total, 10 * math.log10(4.0 / max(mse, 1e-12))))
            if progress:
                progress(it, history[-1][1], history[-1][2])

    desc = desc.detach()
    dens = dens.detach()
    psnr, cosine = evaluate(data, desc, dens, cfg)
    return VoxelGrids(desc, dens, psnr, cosine, history)


def _grid_laplacian(R: int, **kw) -> torch.Tensor:
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


@torch.no_grad()
def _train_lstsq(
    data: TrainingRays,
    cfg: VoxelConfig,
    progress=None,
    device="cpu",
    evaluate_fit: bool = True,
    seed_blocks: Sequence[int] | None = None,
) -> VoxelGrids:
    """Closed-form training: with the densities fixed, a rendered descriptor is linear in the node
    descriptors, p = a G (a: the ray's composite stencil), so the descriptors minimising

        sum_rays w |a G - t|^2 + ridge |G - mean|^2 + tv sum_neighbours |G_i - G_j|^2

    solve one (R^3 x R^3) system per landmark, all landmarks in one batched solve. The rays are all
    S x S patch rays of every observation (a landmark's observations weigh the same; a patch's
    centre ray gets ``centre_rays`` of the patch's weight, as often as the sampled training draws
    it) and all ``prior_bank`` virtual rays of the extrapolation prior (``lstsq_prior_weight`` in
    total; ``tools/bench_novel_view.py`` compares it with Adam)."""
    dev = torch.device(device)
    f32 = dict(dtype=torch.float32, device=dev)
    R, C = cfg.resolution, data.targets.shape[-1]
    R3, L, P = R**3, len(data.centers), data.ray_dirs.shape[1]
    centers = torch.as_tensor(data.centers, **f32)
    sizes = torch.as_tensor(data.sizes, **f32)
    obs_lm = torch.as_tensor(data.obs_landmark, device=dev).long()
    counts = torch.bincount(obs_lm, minlength=L)
    first = torch.cumsum(counts, 0) - counts
    targets = torch.as_tensor(data.targets, device=dev)  # its own dtype (float16 from a build): float32 by chunk
    mean_desc = _track_means(data, obs_lm, L, **f32)
    dens = torch.full((L, R3), math.log(math.expm1(cfg.density_init)), **f32)
    # the densities stay uniform (composite_uniform): softplus of the raw value, as composite takes it
    sigma = float(F.softplus(torch.tensor(math.log(math.expm1(cfg.density_init)))))
    pix_w = torch.full((P,), (1.0 - cfg.centre_rays) / P, **f32)
    pix_w[P // 2] += cfg.centre_rays
    A = torch.zeros(L, R3, R3, **f32)  # sum w a^T a
    B = torch.zeros(L, R3, C, **f32)  # sum w a^T t
    O = len(obs_lm)
    chunk = max(1, cfg.max_batch_rays // max(1, P))
    kept: list[tuple[slice, torch.Tensor]] = []  # the real rays' stencils, for the fit's evaluation ...
    keep = evaluate_fit and O * P * R3 * 4 <= _KEEP_STENCIL_BYTES  # ... unless they would take much memory
    for s in range(0, O, chunk):
        sl = slice(s, min(O, s + chunk))
        lm = obs_lm[sl]
        origins = (torch.as_tensor(data.obs_origin[sl], **f32) - centers[lm]) / sizes[lm, None] + 0.5
        dirs = torch.as_tensor(data.ray_dirs[sl], **f32)
        a, _ = composite_uniform(origins[:, None, :].expand(-1, P, -1), dirs, R, cfg.samples, sigma)  # (n, P, R^3)
        if keep:  # a batch's (O, P, R^3) stencils: ~40 MB for 1,024 fox landmarks
            kept.append((sl, a))
        aw = (a * (pix_w / counts[lm, None].float())[..., None]).transpose(1, 2)
        A.index_add_(0, lm, torch.bmm(aw, a))
        B.index_add_(0, lm, torch.bmm(aw, targets[sl].to(torch.float32)))
        if progress:
            progress(int(0.8 * cfg.iterations * sl.stop / max(O, 1)), float("nan"), float("nan"))
    if cfg.prior_rays > 0 and cfg.lstsq_prior_weight > 0:
        gen = BlockGenerator(seed_blocks or [L], cfg.seed)
        po, pd, pt = _prior_bank(data, cfg, centers, sizes, targets, mean_desc, counts, first, gen)
        step = max(1, cfg.max_batch_rays // max(1, po.shape[1]))
        for s in range(0, L, step):
            ls = slice(s, min(L, s + step))
            a, _ = composite_uniform(po[ls], pd[ls], R, cfg.samples, sigma)
            aw = (a * (cfg.lstsq_prior_weight / po.shape[1])).transpose(1, 2)
            A[ls] += torch.bmm(aw, a)
            B[ls] += torch.bmm(aw, pt[ls])
    A += cfg.lstsq_tv * _grid_laplacian(R, **f32) + cfg.lstsq_ridge * torch.eye(R3, **f32)
    desc = torch.linalg.solve(A, B + cfg.lstsq_ridge * mean_desc[:, None, :])
    if not evaluate_fit:
        return VoxelGrids(desc, dens, np.zeros(0, np.float32), np.zeros(0, np.float32), [])
    psnr, cosine = _fit_quality(data, desc, kept) if keep else evaluate(data, desc, dens, cfg)
    history = []
    if len(psnr):  # one point, the solution's: Adam's data terms and PSNR over the real rays, landmark-weighted
        mse = 4.0 / 10 ** (psnr.astype(np.float64) / 10)  # per descriptor element, as evaluate() has it
        loss = float(np.mean(cfg.mse_weight * C * mse + cfg.cosine_weight * (1.0 - cosine)))
        history.append((cfg.iterations - 1, loss, float(10 * np.log10(4.0 / max(np.mean(mse), 1e-12)))))
    if progress:
        progress(cfg.iterations - 1, float("nan"), float(np.median(psnr)) if len(psnr) else float("nan"))
    return VoxelGrids(desc, dens, psnr, cosine, history)


# the closed form keeps its stencils for the fit's figures up to this size (a batch of 1,024 landmarks
# with 7 x 7 patches: ~40 MB on the fox, ~390 MB with the 72 observations per landmark of a 5,000-frame
# build); beyond it the figures trace the rays again (evaluate), as before
_KEEP_STENCIL_BYTES = 256 << 20


def _fit_quality(data: TrainingRays, desc: torch.Tensor, stencils: list[tuple[slice, torch.Tensor]]):
    """:func:`evaluate` of the closed form's solution from the composite stencils its fit made
    (the densities are fixed, so they are the rendering's): the same figures without tracing every
    ray again (that was 43 % of the fox's closed-form training on two cores)."""
    L, O, C = len(data.centers), len(data.obs_landmark), desc.shape[-1]
    se, cos = torch.zeros(O), torch.zeros(O)
    obs_lm = torch.as_tensor(data.obs_landmark, device=desc.device).long()
    for sl, a in stencils:
        tgt = torch.as_tensor(data.targets[sl], dtype=torch.float32, device=desc.device)
        s_, c_ = _losses(a, desc[obs_lm[sl]], [tgt], (tgt * tgt).sum(-1))
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
        s_, c_ = _losses(a, desc[lm], [tgt], (tgt * tgt).sum(-1))
        se[sl], cos[sl] = (s_.mean(-1) / C).cpu(), c_.mean(-1).cpu()  # per observation (se per element)
    return _per_landmark(data, se, cos, L)
