"""The training stage of the extension: a grown landmark whose grids already render what the new frames saw
of it keeps them (:func:`.budget.unexplained`); the other grown landmarks are fine-tuned (their new
observations' patches sampled, their existing observations' patches rendered from their current grids, Adam
starting from those grids) and the new landmarks trained, in one training."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .budget import unexplained
from .frames import Frames
from .grids import grids_of
from .matching import NewFrames
from .triangulate import Grown, concat_landmarks, shifted

if TYPE_CHECKING:
    from ...triangulation import Landmarks
    from ...voxels.config import TrainingRays, VoxelConfig, VoxelGrids


@dataclass
class Trained:
    """What the training stage trained (:func:`train_landmarks`)."""

    retrain: np.ndarray  # (n_grown,) bool: the grown landmarks trained again (the others keep their grids)
    rays: TrainingRays | None  # the trained landmarks' rays: the retrained grown ones, then the new ones
    grids: VoxelGrids | None  # their trained grids (None: nothing to train)


def train_landmarks(m, lms: Grown, new: NewFrames, frames: Frames, cfg) -> Trained:
    """The training stage (:func:`favormap.voxels.batches.train_batches`, the map's voxel settings ``cfg.voxel``)."""
    from ...voxels.batches import train_batches

    M0 = m.num_frames
    retrain = unexplained(m, lms.grown, lms.grown_rows, M0, new.ff) if lms.n_grown else np.zeros(0, bool)
    gtrain = lms.grown.select(np.flatnonzero(retrain)) if retrain.any() else None
    rays = training_set(m, gtrain, lms.grown_rows[retrain], lms.new, new, frames, cfg)
    grids = train_batches(rays, cfg.voxel, cfg.train_batch) if rays is not None else None
    return Trained(retrain, rays, grids)


@dataclass
class _ObservationRays:
    """The rays of some observations' patches, their training targets and mean targets."""

    origins: np.ndarray  # (O, 3)
    dirs: np.ndarray  # (O, P, 3)
    reach: np.ndarray  # (O,) the patches' reach (voxel sizes)
    targets: np.ndarray  # (O, P, C) float16
    means: np.ndarray  # (O, C) float32


def training_set(m, glms, grown_rows, nlms, new: NewFrames, frames: Frames, cfg) -> TrainingRays | None:
    """The training rays of the landmarks to train: the grown ones ``glms`` (map rows ``grown_rows``; their
    new observations' sampled patches, their existing observations' patches rendered from their current
    grids, Adam starting from those grids), then the new ones ``nlms`` (their sampled patches)."""
    from ...build import training_rays
    from ...triangulation import Landmarks
    from ...voxels.config import TrainingRays
    from ...voxels.rays import patch_rays, voxel_sizes

    M0 = m.num_frames
    all_lms = concat_landmarks(glms, nlms, M0)
    U = len(all_lms)
    if U == 0:
        return None
    v, Ks, poses = cfg.voxel, frames.Ks, frames.cam_from_world
    tr = all_lms.tracks
    tid, fi = tr.track_of_obs, tr.frame_idx
    is_new = fi >= M0
    # the new frames' patches, sampled as a build samples them
    sub = shifted(tr.select(is_new), -M0)
    present = np.unique(tid[is_new])  # every updated landmark has new observations
    lms_new = Landmarks(all_lms.positions[present], sub, np.zeros(len(sub.xy)), np.zeros(len(present)))
    rn = training_rays(
        lms_new, new.ff, new.extractor, v.patch_size, v.box_factor, None, None, v.patch_stride, v.patch_interp
    )
    n_lm = present[rn.obs_landmark]
    old = np.flatnonzero(~is_new)
    ro = _rendered_rays(m, all_lms, grown_rows, old, frames, v, rn)
    obs_lm = np.concatenate([n_lm, tid[old]])
    o = np.argsort(obs_lm, kind="stable")
    # voxel sides over all observations (paper eq. 2)
    reach_new = patch_rays(all_lms.positions, n_lm, sub.frame_idx + M0, Ks, poses, 1)[2]
    sizes = voxel_sizes(np.concatenate([reach_new, ro.reach]), obs_lm, U, v.box_factor)
    init_d = init_s = None
    if glms is not None and len(glms) and v.solver == "adam":
        R3 = m.grid_resolution**3
        init_d = np.full((U, R3, m.channels), np.nan, np.float32)
        init_s = np.full((U, R3), np.nan, np.float32)
        init_d[: len(glms)], init_s[: len(glms)] = grids_of(m, grown_rows)
    return TrainingRays(
        all_lms.positions,
        sizes,
        obs_lm[o].astype(np.int64),
        np.concatenate([rn.obs_origin, ro.origins])[o],
        np.concatenate([rn.ray_dirs, ro.dirs])[o],
        np.concatenate([rn.targets, ro.targets])[o],
        np.concatenate([rn.patch_means(), ro.means])[o],
        init_d,
        init_s,
    )


def _rendered_rays(
    m, all_lms: Landmarks, grown_rows, old: np.ndarray, frames: Frames, v: VoxelConfig, like: TrainingRays
) -> _ObservationRays:
    """The existing observations ``old`` of the grown landmarks (rows of ``all_lms``' tracks): their patches
    as the current grids render them from their own frames, on rays from the landmarks' new positions.
    ``like``: rays whose shapes the empty result takes."""
    import torch

    from ...voxels.config import TrainingRays
    from ...voxels.rays import patch_rays
    from ...voxels.train import render_training_rays

    if not len(old):
        return _ObservationRays(
            np.zeros((0, 3)),
            np.zeros((0,) + like.ray_dirs.shape[1:], np.float32),
            np.zeros(0),
            np.zeros((0,) + like.targets.shape[1:], np.float16),
            np.zeros((0, like.targets.shape[-1]), np.float32),
        )
    Ks, poses = frames.Ks, frames.cam_from_world
    tid, fi = all_lms.tracks.track_of_obs[old], all_lms.tracks.frame_idx[old]
    rows = grown_rows[tid]
    pos_old = np.asarray(m.positions, np.float64)
    oc, od, _ = patch_rays(pos_old, rows, fi, Ks, poses, v.patch_size, v.patch_stride)
    ur, inv = np.unique(rows, return_inverse=True)
    render_data = TrainingRays(
        pos_old[ur],
        np.asarray(m.voxel_size, np.float64)[ur],
        inv.astype(np.int64),
        oc,
        od,
        np.zeros((len(old), od.shape[1], 0), np.float16),
    )
    desc, dens = grids_of(m, ur)
    with torch.no_grad():
        rendered = render_training_rays(render_data, torch.as_tensor(desc), torch.as_tensor(dens), v).numpy()
    # the training rays of those observations start at the landmarks' new positions
    tc, td, reach = patch_rays(all_lms.positions, tid, fi, Ks, poses, v.patch_size, v.patch_stride)
    targets = torch.from_numpy(rendered).half().numpy()
    return _ObservationRays(tc, td, reach, targets, rendered.mean(1, dtype=np.float32))
