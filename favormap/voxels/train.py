"""Training all landmark voxel grids at once (paper sec. 3.3 and supplement "Training and Losses").

(One module for both solvers, Adam and the closed form: they share the rays, the view-extrapolation prior
(:mod:`.prior`) and the evaluation below; Adam's optimiser is in :mod:`.optim`, the losses in :mod:`.losses`,
the settings and stage types in :mod:`.config`.)

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
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F

from .config import TrainingRays, VoxelConfig, VoxelGrids
from .losses import descriptor_losses, ray_loss
from .optim import BatchedAdam, TVGradient, grid_laplacian, node_visibility
from .prior import PriorRays, prior_bank
from .quality import evaluate, fit_quality, render_training_rays
from .render import composite, composite_uniform, ray_stencils, to_local

# the losses, the TV term and the evaluation importable from here, where they were defined before
_losses, _TVGradient = descriptor_losses, TVGradient
__all__ = ["BlockGenerator", "evaluate", "render_training_rays", "train_voxels"]


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


@dataclass
class _Landmarks:
    """The training data's landmarks on the training device, and where each one's observations lie."""

    centers: torch.Tensor  # (L, 3)
    sizes: torch.Tensor  # (L,) box side
    obs_lm: torch.Tensor  # (O,) landmark of each observation (long)
    counts: torch.Tensor  # (L,) observations of each landmark
    first: torch.Tensor  # (L,) its first observation (the observations are grouped by landmark)
    mean_desc: torch.Tensor  # (L, C) unit mean descriptor of its track (_track_means)

    def prior_bank(self, data: TrainingRays, cfg: VoxelConfig, targets: torch.Tensor, gen) -> PriorRays:
        """The view-extrapolation prior's virtual rays of these landmarks (:func:`.prior.prior_bank`)."""
        return prior_bank(data, cfg, self.centers, self.sizes, targets, self.mean_desc, self.counts, self.first, gen)


def _landmarks(data: TrainingRays, dev: torch.device) -> _Landmarks:
    f32 = dict(dtype=torch.float32, device=dev)
    L = len(data.centers)
    obs_lm = torch.as_tensor(data.obs_landmark, device=dev).long()
    counts = torch.bincount(obs_lm, minlength=L)
    return _Landmarks(
        centers=torch.as_tensor(data.centers, **f32),
        sizes=torch.as_tensor(data.sizes, **f32),
        obs_lm=obs_lm,
        counts=counts,
        first=torch.cumsum(counts, 0) - counts,
        mean_desc=_track_means(data, obs_lm, L, **f32),
    )


def _track_means(data: TrainingRays, obs_lm: torch.Tensor, L: int, **f32) -> torch.Tensor:
    """(L, C) unit mean descriptor of each landmark's track, as the map's mean_descriptor: the mean of
    its observations' patch means (:meth:`TrainingRays.patch_means`, from before the float16 rounding)."""
    means = torch.as_tensor(data.patch_means(), **f32)
    return F.normalize(torch.zeros(L, means.shape[-1], **f32).index_add_(0, obs_lm, means), dim=-1)


@dataclass
class _Rays:
    """The rays Adam draws from, as float32 tensors on the training device: the real patch rays of every
    observation and the prior's virtual rays. The patch rays are also kept as flat rows, for one
    index_select per gather (2-4x faster on a CPU than advanced indexing or torch.gather with an
    expanded index; the same values)."""

    origins: torch.Tensor  # (O, 3) each observation's camera centre, in its landmark's local frame
    dirs: torch.Tensor  # (O, P, 3) its patch rays' directions, in local units
    targets: torch.Tensor  # (O, P, C)
    target_sq: torch.Tensor  # (O, P) |target|^2
    prior: PriorRays | None  # (L * V, ...) rows; None without prior rays
    prior_sq: torch.Tensor | None  # (L * V,) |prior target|^2

    @property
    def flat(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(O * P, 3) directions, (O * P, C) targets and (O * P,) |target|^2."""
        return self.dirs.view(-1, 3), self.targets.view(-1, self.targets.shape[-1]), self.target_sq.view(-1)


def _real_rays(data: TrainingRays, lm: _Landmarks, dev: torch.device) -> _Rays:
    f32 = dict(dtype=torch.float32, device=dev)
    # ray origins in each landmark's local frame; directions scaled to local units
    origins = to_local(torch.as_tensor(data.obs_origin, **f32), lm.centers[lm.obs_lm], lm.sizes[lm.obs_lm])
    targets = torch.as_tensor(data.targets, **f32)
    target_sq = (targets * targets).sum(-1)  # (1 for unit descriptors)
    return _Rays(origins, torch.as_tensor(data.ray_dirs, **f32), targets, target_sq, None, None)


def _with_prior(rays: _Rays, prior: PriorRays) -> _Rays:
    """``rays`` with the prior's virtual rays as flat rows."""
    C = prior.targets.shape[-1]
    sq = (prior.targets * prior.targets).sum(-1)
    flat = PriorRays(prior.origins.view(-1, 3), prior.dirs.view(-1, 3), prior.targets.view(-1, C))
    return replace(rays, prior=flat, prior_sq=sq.view(-1))


def _initial_grids(data: TrainingRays, cfg: VoxelConfig, lm: _Landmarks, dev, seed_blocks):
    """The grids Adam starts from (descriptors (L, R^3, C), raw densities (L, R^3), both requiring
    gradients): every node holds the mean descriptor (or zero, or the closed-form fit), the density is
    uniform; a landmark that already has grids (fine-tuning) starts from them."""
    R, C, L = cfg.resolution, data.targets.shape[-1], len(data.centers)
    if cfg.init not in ("mean", "zero", "lstsq"):
        raise ValueError(f"unknown VoxelConfig.init {cfg.init!r} (mean, zero, lstsq)")
    if cfg.init == "lstsq":  # start from the closed-form fit at the initial densities
        fit = _train_lstsq(data, cfg, None, dev, evaluate_fit=False, seed_blocks=seed_blocks)
        desc = fit.descriptors.contiguous().requires_grad_(True)
    else:
        init = lm.mean_desc if cfg.init == "mean" else torch.zeros_like(lm.mean_desc)
        desc = init[:, None, :].repeat(1, R**3, 1).contiguous().requires_grad_(True)
    raw0 = math.log(math.expm1(cfg.density_init))
    dens = torch.full((L, R**3), raw0, dtype=torch.float32, device=dev)
    if data.init_descriptors is not None:  # fine-tuning: the landmarks with grids start from them
        d0 = torch.as_tensor(np.asarray(data.init_descriptors, np.float32).reshape(L, R**3, C), device=dev)
        s0 = torch.as_tensor(np.asarray(data.init_density, np.float32).reshape(L, R**3), device=dev)
        has = torch.isfinite(d0).flatten(1).all(1) & torch.isfinite(s0).all(1)
        with torch.no_grad():
            desc[has] = d0[has]
            dens[has] = s0[has]
    return desc, dens.requires_grad_(True)


def _optimizer(data: TrainingRays, cfg: VoxelConfig, rays: _Rays, desc, dens) -> BatchedAdam:
    """Adam on both grids, each node's learning rate scaled by how many training views see it (relative
    to its landmark's best-seen node; ``cfg.pervoxel_lr``)."""
    L, R3 = desc.shape[:2]
    if cfg.pervoxel_lr:
        vis = node_visibility(data, rays.origins, rays.dirs, cfg.resolution, cfg, desc.device)
        factor = vis / vis.amax(1, keepdim=True).clamp_min(1.0)
    else:
        factor = torch.ones(L, R3, dtype=torch.float32, device=desc.device)
    return BatchedAdam([desc, dens], [cfg.lr_descriptors, cfg.lr_density], [factor, factor])


@dataclass
class _Draw:
    """One iteration's rays: K real ones per landmark (observation and patch row) and Kp prior ones."""

    obs: torch.Tensor  # (L, K) observations
    ray: torch.Tensor  # (L, K) rows of the flat (O * P) patch rays
    prior: torch.Tensor | None  # (L, Kp) virtual rays of each landmark's bank; None without prior rays


def _draw(gen: BlockGenerator, cfg: VoxelConfig, lm: _Landmarks, P: int, dev) -> _Draw:
    K, Kp = cfg.rays_per_landmark, cfg.prior_rays
    r = gen.rand(K).to(dev)
    counts = lm.counts[:, None]
    obs = lm.first[:, None] + torch.minimum((r * counts).long(), counts - 1)
    pix = gen.randint(P, K)
    if cfg.centre_rays > 0:  # a share of the rays through the patch centre
        pix = torch.where(gen.rand(K) < cfg.centre_rays, P // 2, pix)
    ray = obs * P + pix.to(dev)
    return _Draw(obs, ray, gen.randint(cfg.prior_bank, Kp).to(dev) if Kp > 0 else None)


def _group_rays(rays: _Rays, draw: _Draw, gs: slice, cfg: VoxelConfig):
    """The drawn rays of landmarks ``gs``: origins and directions (G, K + Kp, 3), targets as (G, K, C)
    and (G, Kp, C) blocks, |target|^2 (G, K + Kp)."""
    G, K, Kp, dev = gs.stop - gs.start, cfg.rays_per_landmark, cfg.prior_rays, draw.obs.device
    dirs_flat, targets_flat, tsq_flat = rays.flat
    C = targets_flat.shape[-1]
    rg = draw.ray[gs].reshape(-1)
    o = rays.origins.index_select(0, draw.obs[gs].reshape(-1)).view(G, K, 3)
    d = dirs_flat.index_select(0, rg).view(G, K, 3)
    tgts = [targets_flat.index_select(0, rg).view(G, K, C)]
    tn2 = tsq_flat.index_select(0, rg).view(G, K)
    if Kp > 0:
        pb = rays.prior
        pr = (torch.arange(gs.start, gs.stop, device=dev)[:, None] * cfg.prior_bank + draw.prior[gs]).reshape(-1)
        o = torch.cat([o, pb.origins.index_select(0, pr).view(G, Kp, 3)], 1)
        d = torch.cat([d, pb.dirs.index_select(0, pr).view(G, Kp, 3)], 1)
        tgts.append(pb.targets.index_select(0, pr).view(G, Kp, C))
        tn2 = torch.cat([tn2, rays.prior_sq.index_select(0, pr).view(G, Kp)], 1)
    return o, d, tgts, tn2


def _optimise(
    cfg: VoxelConfig, rays: _Rays, lm: _Landmarks, desc, dens, opt: BatchedAdam, gen: BlockGenerator, progress
) -> list:
    """Adam's iterations on ``desc`` and ``dens`` (in place); returns the training curve, (iteration, loss,
    PSNR of the real rays) every 25 iterations and at the last."""
    L, P, C = len(lm.centers), rays.dirs.shape[1], rays.targets.shape[-1]
    R, K, Kp, dev = cfg.resolution, cfg.rays_per_landmark, cfg.prior_rays, desc.device
    f32 = dict(dtype=torch.float32, device=dev)
    ray_w = torch.cat([torch.ones(K, **f32), torch.full((Kp,), cfg.prior_weight, **f32)])
    norm = float(L * ray_w.sum())  # loss = weighted mean over all rays of all landmarks
    group = cfg.per_batch(K + Kp)
    history = []
    tv_start = int(cfg.iterations * cfg.tv_from)
    tv_grad = TVGradient(R, L, C, dev) if cfg.tv_weight > 0 else None
    for it in range(cfg.iterations):
        draw = _draw(gen, cfg, lm, P, dev)
        total, se_real = 0.0, 0.0
        for g0 in range(0, L, group):
            gs = slice(g0, min(L, g0 + group))
            o, d, tgts, tn2 = _group_rays(rays, draw, gs, cfg)
            st, delta, hit = ray_stencils(o, d, R, cfg.samples)
            a, opacity = composite(st, delta, dens[gs], hit)  # (G,K,R^3): pred = a @ desc
            se, cos = descriptor_losses(a, desc[gs], tgts, tn2)
            loss = ray_loss(cfg, se, cos, opacity, hit.float() * ray_w, norm)
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
    return history


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
    lm = _landmarks(data, dev)
    rays = _real_rays(data, lm, dev)
    desc, dens = _initial_grids(data, cfg, lm, dev, seed_blocks)
    opt = _optimizer(data, cfg, rays, desc, dens)
    if cfg.prior_rays > 0:
        rays = _with_prior(rays, lm.prior_bank(data, cfg, rays.targets, gen))
    history = _optimise(cfg, rays, lm, desc, dens, opt, gen, progress)
    desc = desc.detach()
    dens = dens.detach()
    psnr, cosine = evaluate(data, desc, dens, cfg)
    return VoxelGrids(desc, dens, psnr, cosine, history)


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
    lms = _landmarks(data, dev)
    obs_lm, counts = lms.obs_lm, lms.counts
    targets = torch.as_tensor(data.targets, device=dev)  # its own dtype (float16 from a build): float32 by chunk
    dens = torch.full((L, R3), math.log(math.expm1(cfg.density_init)), **f32)
    # the densities stay uniform (composite_uniform): softplus of the raw value, as composite takes it
    sigma = float(F.softplus(torch.tensor(math.log(math.expm1(cfg.density_init)))))
    pix_w = torch.full((P,), (1.0 - cfg.centre_rays) / P, **f32)
    pix_w[P // 2] += cfg.centre_rays
    A = torch.zeros(L, R3, R3, **f32)  # sum w a^T a
    B = torch.zeros(L, R3, C, **f32)  # sum w a^T t
    O = len(obs_lm)
    chunk = cfg.per_batch(max(1, P))
    kept: list[tuple[slice, torch.Tensor]] = []  # the real rays' stencils, for the fit's evaluation ...
    keep = evaluate_fit and O * P * R3 * 4 <= _KEEP_STENCIL_BYTES  # ... unless they would take much memory
    for s in range(0, O, chunk):
        sl = slice(s, min(O, s + chunk))
        lm = obs_lm[sl]
        origins = to_local(torch.as_tensor(data.obs_origin[sl], **f32), lms.centers[lm], lms.sizes[lm])
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
        prior = lms.prior_bank(data, cfg, targets, gen)
        V = prior.origins.shape[1]
        step = cfg.per_batch(max(1, V))
        for s in range(0, L, step):
            ls = slice(s, min(L, s + step))
            a, _ = composite_uniform(prior.origins[ls], prior.dirs[ls], R, cfg.samples, sigma)
            aw = (a * (cfg.lstsq_prior_weight / V)).transpose(1, 2)
            A[ls] += torch.bmm(aw, a)
            B[ls] += torch.bmm(aw, prior.targets[ls])
    A += cfg.lstsq_tv * grid_laplacian(R, **f32) + cfg.lstsq_ridge * torch.eye(R3, **f32)
    desc = torch.linalg.solve(A, B + cfg.lstsq_ridge * lms.mean_desc[:, None, :])
    if not evaluate_fit:
        return VoxelGrids(desc, dens, np.zeros(0, np.float32), np.zeros(0, np.float32), [])
    psnr, cosine = fit_quality(data, desc, kept) if keep else evaluate(data, desc, dens, cfg)
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
