"""The voxels' settings (:class:`VoxelConfig`, its quality presets and the per-extractor defaults) and
the stage boundaries of training: the rays it trains on (:class:`TrainingRays`) and the trained grids
(:class:`VoxelGrids`). Neither numpy nor torch is imported: the CLI reads the defaults from here."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy and torch only in annotations: the CLI imports this module to show the defaults
    import numpy as np
    import torch

    from ..features.base import ExtractorPolicy


@dataclass
class VoxelConfig:
    """Model and training settings of the per-landmark voxels (all landmarks train together)."""

    # -- model ------------------------------------------------------------------------------
    resolution: int = 3  # R: nodes per axis of each landmark's grid
    patch_size: int = 7  # S: training patch S x S pixels around each observation
    # described every patch_stride pixels from the centre out to the patch's edges (1: every pixel;
    # S = 7 with stride 3: a 3 x 3 grid spanning the same 7 x 7 pixels, 5.4x fewer descriptors)
    patch_stride: int = 1
    # describe only some pixels of each patch (the centre 3 x 3, every second pixel beyond, the edges:
    # 25 of 49 for S = 7) and interpolate the others (favormap.features.base.patch_interpolation).
    # None: the extractor's (ExtractorPolicy.patch_interp; build_map resolves it, voxel_config_for)
    patch_interp: bool | None = None
    # the stored mean descriptor (the prior-free step's and the "mean" baseline's) averages the central
    # mean_patch x mean_patch pixels of each patch (0: the whole patch)
    mean_patch: int = 0
    box_factor: float = 7.0  # voxel side = box_factor * min_i l_ij / f_i (paper eq. 2: S; reference code: 12)
    samples: int = 12  # N samples per ray (training and rendering)
    density_init: float = 1.0  # initial sigma per voxel side, uniform
    init: str = "mean"  # initial node descriptors (adam): "mean" (track mean), "zero", "lstsq" (the closed form)
    # -- optimisation -----------------------------------------------------------------------
    # "adam": gradient descent on descriptors and densities (the paper's training).
    # "lstsq" (the "quick" preset): densities stay at density_init and the node descriptors are
    # the closed-form least-squares fit of every patch ray and every virtual prior ray (one small
    # linear system per landmark; the fields below down to pervoxel_lr, and the loss weights, do
    # not apply): a fraction of Adam's time, nearly its accuracy (docs/implementation-notes.md)
    solver: str = "adam"
    lstsq_prior_weight: float = 2.0  # total weight of a landmark's virtual rays, its real rays weighing 1
    lstsq_ridge: float = 1e-3  # pull of every node towards the landmark's mean descriptor
    lstsq_tv: float = 1e-3  # smoothness: squared differences of neighbouring nodes
    iterations: int = 200
    rays_per_landmark: int = 32  # rays drawn per landmark per iteration
    centre_rays: float = 0.5  # fraction of them through the patch centre (the ray the localizer renders)
    lr_descriptors: float = 0.01
    lr_density: float = 0.1
    lr_final: float = 0.1  # learning-rate factor at the last iteration (exponential decay from 1)
    pervoxel_lr: bool = True  # scale a node's rate by how many training views touch it (DVGO / FaVoR)
    mse_weight: float = 1.0  # squared L2 (summed over channels) of rendered vs extracted
    cosine_weight: float = 1.0  # 1 - cosine of rendered vs extracted
    tv_weight: float = 1e-3  # total variation on both grids ...
    tv_from: float = 0.75  # ... from this fraction of the iterations on
    entropy_weight: float = 1e-3  # entropy of the accumulated opacity
    # -- view-extrapolation prior: virtual centre rays from directions around the training views
    prior_rays: int = 16  # virtual rays per landmark per iteration (in addition to rays_per_landmark)
    prior_bank: int = 64  # virtual directions drawn once per landmark
    prior_spread_deg: float = 45.0  # angle between a virtual direction and its training view, uniform in [0, this]
    prior_kernel_deg: float = 1.0  # target = Gaussian-in-angle blend of the nearest training views' descriptors
    prior_weight: float = 1.0  # loss weight of a virtual ray relative to a real one
    # angle scale (deg) over which the prior's target moves from the nearest views to the landmark's
    # mean descriptor: weight of the views exp(-a / this), a = angle to the nearest training view.
    # 0: never (pure nearest views); None: the extractor's (ExtractorPolicy.view_prior_deg; build_map resolves it)
    prior_mean_deg: float | None = None
    # -- execution ----------------------------------------------------------------------------
    max_batch_rays: int = 1 << 18  # rays rendered per forward pass (landmark groups; memory bound)
    seed: int = 0

    def per_batch(self, rays_each: int) -> int:
        """How many landmarks (or observations) of ``rays_each`` rays each one forward pass takes within
        ``max_batch_rays``: at least one."""
        return max(1, self.max_batch_rays // rays_each)

    @classmethod
    def preset(cls, quality: str = "fast", **overrides) -> VoxelConfig:
        """A config of a quality preset (``QUALITY_PRESETS``) with some fields overridden."""
        if quality not in QUALITY_PRESETS:
            raise ValueError(f"unknown voxel quality {quality!r} (choose from {', '.join(QUALITY_PRESETS)})")
        return cls(**{**QUALITY_PRESETS[quality], **overrides})


def voxel_config_for(cfg: VoxelConfig, extractor: str | ExtractorPolicy) -> VoxelConfig:
    """``cfg`` with its per-extractor defaults (None fields: ``prior_mean_deg``, ``patch_interp``) filled in
    from the extractor's policy (a registered name, or the policy itself), as a build records them in the map's
    provenance."""
    from ..features.base import ExtractorPolicy, policy_of

    policy = extractor if isinstance(extractor, ExtractorPolicy) else policy_of(extractor)
    if cfg.prior_mean_deg is None:
        cfg = replace(cfg, prior_mean_deg=policy.view_prior_deg)
    if cfg.patch_interp is None:  # only a full patch (stride 1) of odd size has the pixels to interpolate from
        whole = cfg.patch_stride == 1 and cfg.patch_size % 2 == 1
        cfg = replace(cfg, patch_interp=whole and policy.patch_interp)
    return cfg


QUALITY_PRESETS: dict[str, dict] = {
    # the dataclass's defaults: Adam on the rendering loss (the learned extractors' preset)
    "fast": {},
    # closed-form descriptors at fixed densities from 3 x 3 patches: speed first. The initial (= fixed)
    # density of 20 per voxel side makes the cubes nearly opaque, so a ray's descriptor interpolates the nodes
    # on the side facing the camera and depends on the view
    "quick": dict(solver="lstsq", patch_size=3, density_init=20.0),
    # the closed form on the full 7 x 7 patches, pulled towards the track mean (ridge 0.03 instead of 0.001:
    # the nodes few rays constrain keep the mean instead of fitting them); SIFT's preset: it localizes as Adam
    # does in less time (docs/implementation-notes.md)
    "balanced": dict(solver="lstsq", patch_size=7, density_init=20.0, lstsq_ridge=0.03),
    "reference": dict(
        solver="adam",
        iterations=2000,
        rays_per_landmark=1024,
        prior_rays=512,
        box_factor=12.0,
        lr_final=0.1 ** (2000 / 10000),
        tv_from=0.75,
    ),
}


@dataclass
class TrainingRays:
    """Training data: every observation contributes S*S rays (one per patch pixel)."""

    centers: np.ndarray  # (L, 3) landmark positions (world)
    sizes: np.ndarray  # (L,) voxel side lengths (world)
    obs_landmark: np.ndarray  # (O,) landmark of each observation, sorted
    obs_origin: np.ndarray  # (O, 3) camera centre (world)
    ray_dirs: np.ndarray  # (O, S*S, 3) world directions of the patch pixels
    # (O, S*S, C) descriptors extracted at the patch pixels (unit norm): float16 from a build (half the
    # memory of the build's largest array; rounding < 2.5e-4 per element), float32 accepted; training
    # computes in float32, chunk by chunk
    targets: np.ndarray
    # (O, C) float32 mean of each observation's patch descriptors, as the build computed it from the
    # float32 descriptors before rounding the targets (None: patch_means computes it from the targets)
    target_means: np.ndarray | None = None
    # (L, R^3, C) and (L, R^3) grids to start Adam from (fine-tuning trained landmarks; rows of NaN: the
    # landmarks without, which start as VoxelConfig.init says). None: every landmark starts as init says
    init_descriptors: np.ndarray | None = None
    init_density: np.ndarray | None = None

    def patch_means(self) -> np.ndarray:
        """(O, C) float32 mean descriptor of each observation's patch (not normalised)."""
        if self.target_means is not None:
            return self.target_means
        import numpy as np

        return self.targets.mean(1, dtype=np.float32)


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
