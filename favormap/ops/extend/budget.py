"""Which landmarks the extended map keeps (the build's landmark budget) and which grown landmarks
are trained again."""

from __future__ import annotations

import numpy as np

from .grids import render_towards, unit


def within_budget(m, glms, grown_rows: np.ndarray, nlms, budget: int, min_frame_landmarks: int, M0: int):
    """The landmarks of the extended map within ``budget``, chosen as a build chooses them
    (:func:`favormap.build.landmark_budget`: the longest tracks, then the lowest mean reprojection error,
    then the best remaining tracks of frames that see fewer than ``min_frame_landmarks``) among the map's
    untouched landmarks, the grown ones (their tracks as grown) and the new ones (of new frames, numbered
    from ``M0``).

    Returns the grown landmarks kept (and their map rows), the new ones kept, and the sorted rows of the
    map's landmarks left out (untouched or grown)."""
    from ...build import landmark_budget

    L0 = m.num_landmarks
    untouched = np.ones(L0, bool)
    untouched[grown_rows] = False
    old = np.flatnonzero(untouched)
    n_g = 0 if glms is None else len(glms)
    n_n = 0 if nlms is None else len(nlms)
    if len(old) + n_g + n_n <= budget:
        return glms, grown_rows, nlms, np.zeros(0, np.int64)
    empty = np.zeros(0, np.int64)
    length = np.concatenate(
        [
            np.asarray(m.track_length, np.int64)[old],
            glms.tracks.lengths if n_g else empty,
            nlms.tracks.lengths if n_n else empty,
        ]
    )
    error = np.concatenate(
        [
            np.asarray(m.reproj_error, np.float64)[old],
            glms.mean_reproj_error if n_g else np.zeros(0),
            nlms.mean_reproj_error if n_n else np.zeros(0),
        ]
    )
    # every candidate's observations: (candidate, frame of the extended map)
    old_tl, old_tf = np.asarray(m.track_landmark, np.int64), np.asarray(m.track_frame, np.int64)
    pos = np.full(L0, -1, np.int64)
    pos[old] = np.arange(len(old))
    on_old = pos[old_tl] >= 0
    obs_lm = np.concatenate(
        [
            pos[old_tl[on_old]],
            glms.tracks.track_of_obs + len(old) if n_g else empty,
            nlms.tracks.track_of_obs + len(old) + n_g if n_n else empty,
        ]
    )
    obs_frame = np.concatenate(
        [old_tf[on_old], glms.tracks.frame_idx if n_g else empty, nlms.tracks.frame_idx + M0 if n_n else empty]
    )
    keep, _ = landmark_budget(length, error, obs_lm, obs_frame, budget, min_frame_landmarks)
    k_old, k_g, k_n = np.split(keep, [len(old), len(old) + n_g])
    dropped = np.sort(np.concatenate([old[~k_old], grown_rows[~k_g]]))
    if n_g:
        glms = glms.select(np.flatnonzero(k_g)) if k_g.any() else None
        grown_rows = grown_rows[k_g]
    if n_n:
        nlms = nlms.select(np.flatnonzero(k_n)) if k_n.any() else None
    return glms, grown_rows, nlms, dropped


def unexplained(m, glms, grown_rows: np.ndarray, M0: int, ff) -> np.ndarray:
    """(len(glms),) bool: the grown landmarks whose grids must be trained again. A grown landmark keeps its
    grids when they already render what the new frames saw of it: the descriptor of each of its new
    observations' keypoints has at least the cosine with the descriptor its grids render towards that
    frame that its training patches had with their renderings (``cosine``, its fit). Its position, track and
    view cone are updated either way."""
    tr = glms.tracks
    new = np.flatnonzero(tr.frame_idx >= M0)
    j, f, k = tr.track_of_obs[new], tr.frame_idx[new] - M0, tr.keypoint_idx[new]
    rows = grown_rows[j]
    ok = np.zeros(len(new), bool)
    order = np.argsort(f, kind="stable")
    bounds = np.searchsorted(f[order], np.arange(len(ff.features) + 1))
    for frame in range(len(ff.features)):
        sel = order[bounds[frame] : bounds[frame + 1]]
        if not len(sel):
            continue
        r = rows[sel]
        rendered = render_towards(m, r, ff.cam_from_world[frame])
        seen = unit(np.asarray(ff.features[frame].descriptors, np.float32)[k[sel]])
        ok[sel] = np.einsum("ij,ij->i", rendered, seen) >= np.asarray(m.cosine, np.float32)[r]
    return np.bincount(j[~ok], minlength=len(glms)) > 0
