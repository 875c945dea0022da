"""The extended map's arrays."""

from __future__ import annotations

import dataclasses

import numpy as np


def _patches(m, keep_old, all_lms, M0: int, seq, ff, cfg) -> np.ndarray:
    """The stored observation pixels (tracks/patch) of the output's observations, in the order
    ``_extend`` lists them: the untouched landmarks' as stored, then the updated landmarks' (existing
    observations: as stored, found by their row; new ones: cut from the new frames' images)."""
    from ...build import observation_patches
    from ...tracking import Tracks
    from ...triangulation import Landmarks

    stored = np.asarray(m.track_patch)
    tr = all_lms.tracks
    is_new = tr.frame_idx >= M0
    out = np.empty((len(tr.xy),) + stored.shape[1:], np.uint8)
    out[~is_new] = stored[tr.keypoint_idx[~is_new]]
    if is_new.any():
        n = int(is_new.sum())
        sub = Tracks(tr.frame_idx[is_new] - M0, tr.keypoint_idx[is_new], tr.xy[is_new], np.array([0, n]))
        lms = Landmarks(np.zeros((1, 3)), sub, np.zeros(len(sub.xy)), np.zeros(1))
        radius = (stored.shape[1] - 1) // 2
        out[is_new] = observation_patches(lms, seq, ff, dataclasses.replace(cfg, align_patches=radius))
    return np.concatenate([stored[keep_old], out])
