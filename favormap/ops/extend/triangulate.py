"""The triangulation stage of the extension: the map's landmarks that gained observations triangulated
again from all of them, the new frames' other tracks triangulated into new landmarks, then the landmark
budget (:func:`.budget.within_budget`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..extend_config import ExtendConfig
from .budget import within_budget
from .frames import Frames
from .matching import Attachment, NewFrames

if TYPE_CHECKING:
    from ...tracking import Tracks
    from ...triangulation import Landmarks


@dataclass
class Grown:
    """The landmarks the new frames change, within the landmark budget (:func:`triangulate_landmarks`)."""

    grown: Landmarks | None  # the map's landmarks that gained observations, frames of the extended map
    grown_rows: np.ndarray  # (len(grown),) their rows in the map
    new: Landmarks | None  # the new frames' own tracks, frames of the new sequence
    dropped: np.ndarray  # sorted rows of the map's landmarks left out of the budget (untouched or grown)
    observations_added: int  # the grown landmarks' observations from the new frames

    @property
    def n_grown(self) -> int:
        return 0 if self.grown is None else len(self.grown)

    @property
    def n_new(self) -> int:
        return 0 if self.new is None else len(self.new)


def triangulate_landmarks(m, new: NewFrames, att: Attachment, frames: Frames, cfg, config: ExtendConfig) -> Grown:
    """The triangulation stage: the grown landmarks from all their observations (:func:`regrow`), new
    landmarks from the new tracks that joined none, then the ones the landmark budget keeps. ``cfg``: the
    map's build config."""
    from ...build import triangulate_tracks

    M0 = m.num_frames
    glms, grown_rows = regrow(m, att, new.ff, frames, cfg)
    free = np.flatnonzero(att.joined < 0)
    keep_obs = np.isin(new.tracks.track_of_obs, free)
    ntr = new.tracks.select(keep_obs)
    nlms = triangulate_tracks(ntr, new.ff, cfg) if len(ntr) else None
    nlms = nlms if nlms is not None and len(nlms) else None
    budget = cfg.max_landmarks if config.max_landmarks is None else config.max_landmarks
    glms, grown_rows, nlms, dropped = within_budget(m, glms, grown_rows, nlms, budget, cfg.min_frame_landmarks, M0)
    added = 0 if glms is None else int((glms.tracks.frame_idx >= M0).sum())
    return Grown(glms, grown_rows, nlms, dropped, added)


def regrow(m, att: Attachment, ff, frames: Frames, cfg) -> tuple[Landmarks | None, np.ndarray]:
    """The map's landmarks with attached observations triangulated again from all their observations
    (observations that no longer fit dropped), and their map rows; a landmark stays grown only while some of
    its new observations fit. The existing observations carry their observation row as keypoint index (so
    their stored patches can be found)."""
    from ...tracking import Tracks
    from ...triangulation import triangulate

    L0, M0 = m.num_landmarks, m.num_frames
    tri_cfg = cfg.triangulation()
    grown = np.unique(att.landmark)
    old_tl, old_tf, old_xy = np.asarray(m.track_landmark), np.asarray(m.track_frame), np.asarray(m.track_xy)
    slot = np.full(L0, -1, np.int64)
    slot[grown] = np.arange(len(grown))
    old_sel = np.flatnonzero(slot[old_tl] >= 0)
    kps = [np.asarray(feats.keypoints, np.float64) for feats in ff.features]
    new_xy = np.concatenate([kp[att.keypoint[att.frame == f]] for f, kp in enumerate(kps)] or [np.zeros((0, 2))])
    order = np.argsort(att.frame, kind="stable")  # new_xy is by frame
    add_l, add_f, add_k = att.landmark[order], att.frame[order], att.keypoint[order]
    gt = Tracks.from_obs(
        np.concatenate([old_tf[old_sel], add_f + M0]),
        np.concatenate([old_sel, add_k]),
        np.concatenate([old_xy[old_sel].astype(np.float64), new_xy]),
        np.concatenate([slot[old_tl[old_sel]], slot[add_l]]),
    )
    glms = triangulate(gt, frames.cam_from_world, frames.Ks, tri_cfg) if len(gt) else None
    if glms is None or not len(glms):
        return None, np.zeros(0, np.int64)
    new_obs = glms.tracks.frame_idx >= M0
    has_new = np.bincount(glms.tracks.track_of_obs[new_obs], minlength=len(glms)) > 0
    glms = glms.select(np.flatnonzero(has_new))
    return glms, grown[glms.source]


def shifted(tracks: Tracks, frames: int) -> Tracks:
    """``tracks`` with their frame indices moved by ``frames``."""
    from ...tracking import Tracks

    return Tracks(tracks.frame_idx + frames, tracks.keypoint_idx, tracks.xy, tracks.offsets)


def concat_landmarks(glms, nlms, M0: int) -> Landmarks:
    """The grown landmarks (frames of the whole map) and the new ones (new frames, shifted by ``M0``)
    as one Landmarks over all frames."""
    from ...tracking import Tracks
    from ...triangulation import Landmarks

    parts = []
    if glms is not None:
        parts.append(glms)
    if nlms is not None:
        parts.append(Landmarks(nlms.positions, shifted(nlms.tracks, M0), nlms.reproj_errors, nlms.angles_deg))
    if not parts:
        none = np.zeros(0, np.int64)
        return Landmarks(np.zeros((0, 3)), Tracks.from_obs(none, none, np.zeros((0, 2)), none), np.zeros(0), none)
    return Landmarks(
        np.concatenate([p.positions for p in parts]),
        Tracks.concat([p.tracks for p in parts]),
        np.concatenate([p.reproj_errors for p in parts]),
        np.concatenate([p.angles_deg for p in parts]),
    )
