"""The training set of the extension: the grown landmarks' rays (new observations sampled, existing ones
rendered from their current grids) and the new landmarks'."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .grids import grids_of


def _concat_landmarks(glms, nlms, M0: int):
    """The grown landmarks (frames of the whole map) and the new ones (new frames, shifted by ``M0``)
    as one Landmarks over all frames."""
    from ...tracking import Tracks
    from ...triangulation import Landmarks

    parts = []
    if glms is not None:
        parts.append(glms)
    if nlms is not None:
        t = nlms.tracks
        parts.append(
            Landmarks(
                nlms.positions,
                Tracks(t.frame_idx + M0, t.keypoint_idx, t.xy, t.offsets),
                nlms.reproj_errors,
                nlms.angles_deg,
            )
        )
    if not parts:
        none = np.zeros(0, np.int64)
        return Landmarks(np.zeros((0, 3)), Tracks.from_obs(none, none, np.zeros((0, 2)), none), np.zeros(0), none)
    return Landmarks(
        np.concatenate([p.positions for p in parts]),
        Tracks.concat([p.tracks for p in parts]),
        np.concatenate([p.reproj_errors for p in parts]),
        np.concatenate([p.angles_deg for p in parts]),
    )


@dataclass
class _Update:
    rays: object  # TrainingRays of the grown, then the new landmarks


def _training_set(m, glms, grown_rows, nlms, M0, ff, poses, Ks, cfg, extractor):
    """The training rays of the landmarks to train: the grown ones (their new observations' sampled
    patches, their existing observations' patches rendered from their current grids, Adam starting from
    those grids), then the new ones (their sampled patches)."""
    import torch

    from ...build import training_rays
    from ...tracking import Tracks
    from ...triangulation import Landmarks
    from ...voxels.config import TrainingRays
    from ...voxels.rays import patch_rays, voxel_sizes
    from ...voxels.train import render_training_rays

    all_lms = _concat_landmarks(glms, nlms, M0)
    U = len(all_lms)
    if U == 0:
        return None
    v = cfg.voxel
    tr = all_lms.tracks
    tid, fi = tr.track_of_obs, tr.frame_idx
    is_new = fi >= M0
    # the new frames' patches, sampled as a build samples them
    sub = tr.select(is_new)
    sub = Tracks(sub.frame_idx - M0, sub.keypoint_idx, sub.xy, sub.offsets)
    present = np.unique(tid[is_new])  # every updated landmark has new observations
    lms_new = Landmarks(all_lms.positions[present], sub, np.zeros(len(sub.xy)), np.zeros(len(present)))
    rn = training_rays(lms_new, ff, extractor, v.patch_size, v.box_factor, None, None, v.patch_stride, v.patch_interp)
    n_lm = present[rn.obs_landmark]
    # the existing observations' patches, as the current grids render them from their own frames
    old = np.flatnonzero(~is_new)
    if len(old):
        rows = grown_rows[tid[old]]
        pos_old = np.asarray(m.positions, np.float64)
        oc, od, _ = patch_rays(pos_old, rows, fi[old], Ks, poses, v.patch_size, v.patch_stride)
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
        tc, td, reach_old = patch_rays(all_lms.positions, tid[old], fi[old], Ks, poses, v.patch_size, v.patch_stride)
        old_targets = torch.from_numpy(rendered).half().numpy()
        old_means = rendered.mean(1, dtype=np.float32)
    else:
        tc = np.zeros((0, 3))
        td = np.zeros((0,) + rn.ray_dirs.shape[1:], np.float32)
        reach_old = np.zeros(0)
        old_targets = np.zeros((0,) + rn.targets.shape[1:], np.float16)
        old_means = np.zeros((0, rn.targets.shape[-1]), np.float32)
    obs_lm = np.concatenate([n_lm, tid[old]])
    o = np.argsort(obs_lm, kind="stable")
    # voxel sides over all observations (paper eq. 2)
    reach_new = patch_rays(all_lms.positions, n_lm, sub.frame_idx + M0, Ks, poses, 1)[2]
    sizes = voxel_sizes(np.concatenate([reach_new, reach_old]), obs_lm, U, v.box_factor)
    init_d = init_s = None
    if glms is not None and len(glms) and v.solver == "adam":
        R3 = m.grid_resolution**3
        init_d = np.full((U, R3, m.channels), np.nan, np.float32)
        init_s = np.full((U, R3), np.nan, np.float32)
        init_d[: len(glms)], init_s[: len(glms)] = grids_of(m, grown_rows)
    rays = TrainingRays(
        all_lms.positions,
        sizes,
        obs_lm[o].astype(np.int64),
        np.concatenate([rn.obs_origin, tc])[o],
        np.concatenate([rn.ray_dirs, td])[o],
        np.concatenate([rn.targets, old_targets])[o],
        np.concatenate([rn.patch_means(), old_means])[o],
        init_d,
        init_s,
    )
    return _Update(rays)
