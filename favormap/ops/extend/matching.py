"""Matching the new frames to the map's landmarks: each landmark projected into a new frame takes the most
similar keypoint near its projection; the new tracks with such keypoints join those landmarks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..extend_config import ExtendConfig
from .grids import render_towards, unit

if TYPE_CHECKING:
    from ...extraction import ExtractorSpec, FrameFeatures
    from ...tracking import Tracks


@dataclass
class NewFrames:
    """The new frames' features (extracted with the map's extractor settings) and their tracks among
    themselves (:func:`favormap.build.track_frames`): what the matching starts from."""

    ff: FrameFeatures
    tracks: Tracks
    extractor: ExtractorSpec


@dataclass
class Attachment:
    """The new frames' observations of the map's landmarks (:func:`attach`)."""

    joined: np.ndarray  # (len(tracks),) the landmark each new track joins (-1: none, it makes a new one)
    landmark: np.ndarray  # (A,) map row of each attached observation, one per landmark and new frame
    frame: np.ndarray  # (A,) its new frame
    keypoint: np.ndarray  # (A,) its keypoint in that frame
    radius_px: float  # the projection matching radius used (match_radius)
    min_similarity: float  # the least descriptor similarity used


def attach(m, new: NewFrames, cfg, config: ExtendConfig) -> Attachment:
    """The matching stage: the new frames' keypoints matched to the map ``m``'s landmarks
    (:func:`match_landmarks`), then the new tracks with matched keypoints joined to them (:func:`attach_tracks`).
    ``cfg``: the map's build config."""
    min_sim = cfg.min_similarity if config.min_similarity is None else config.min_similarity
    radius = match_radius(m, cfg, config)
    match_l, match_f, match_k = match_landmarks(m, new.ff, config, min_sim, radius)
    counts = np.array([len(f.keypoints) for f in new.ff.features], np.int64)
    base = np.concatenate([[0], np.cumsum(counts)])
    joined, (add_l, add_f, add_k) = attach_tracks(new.tracks, m.num_landmarks, base, match_l, match_f, match_k)
    return Attachment(joined, add_l, add_f, add_k, radius, min_sim)


def match_radius(m, cfg, config: ExtendConfig) -> float:
    """The projection matching radius (px): ExtendConfig's, else the epipolar limit of the map's tracking
    (its build config's, else the one its build measured), else the extractor's keypoint precision."""
    from ...build_config import default_max_epipolar

    if config.match_radius_px is not None:
        return float(config.match_radius_px)
    measured = (m.provenance.get("stats") or {}).get("max_epipolar_px")
    for r in (cfg.max_epipolar_px, measured):
        if r is not None and np.isfinite(r) and r > 0:
            return float(r)
    return float(default_max_epipolar(cfg.extractor))


def match_landmarks(
    m, ff, config: ExtendConfig, min_similarity: float, radius_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints of the new frames ``ff`` (FrameFeatures) that observe landmarks of the map ``m``
    (MapData): (landmark row, frame, keypoint) of each match, all landmarks of a frame at once."""
    from ...geometry import project
    from ...localize.matching import radius_pairs
    from ...visibility import ViewLimits, visible_mask

    limits = ViewLimits(angle_margin_deg=config.view_cone_deg)
    mean_desc = unit(m.mean_descriptor)
    out_l, out_f, out_k = [], [], []
    for f in range(len(ff.features)):
        feats = ff.features[f]
        kp = np.asarray(feats.keypoints, np.float64)
        if not len(kp):
            continue
        cam, T = ff.cameras[f], ff.cam_from_world[f]
        rows = np.flatnonzero(visible_mask(m.positions, cam, T, m.view_dir, m.view_angle, m.depth_range, limits))
        if not len(rows):
            continue
        # only the pairs within the radius are compared: the landmarks with a keypoint that near are rendered
        li, kj = radius_pairs(project(cam.K, T, m.positions[rows]), kp, radius_px)
        if not len(li):
            continue
        near, li = np.unique(li, return_inverse=True)
        rows = rows[near]
        D = np.ascontiguousarray(feats.descriptors, np.float32)
        rendered = unit(render_towards(m, rows, T))
        sim = np.maximum(np.einsum("ij,ij->i", mean_desc[rows][li], D[kj]), np.einsum("ij,ij->i", rendered[li], D[kj]))
        ok = sim >= min_similarity
        li, kj, sim = li[ok], kj[ok], sim[ok]
        # each landmark's most similar keypoint (ties: the lower keypoint index)
        o = np.lexsort((kj, -sim, li))
        first = np.r_[True, li[o][1:] != li[o][:-1]] if len(o) else np.zeros(0, bool)
        lm, k, s = rows[li[o][first]], kj[o][first], sim[o][first]
        if not len(lm):
            continue
        # a keypoint claimed by several landmarks goes to the most similar one
        o = np.lexsort((-s, k))
        first = np.r_[True, k[o][1:] != k[o][:-1]]
        out_l.append(lm[o][first])
        out_k.append(k[o][first])
        out_f.append(np.full(int(first.sum()), f, np.int64))
    if not out_l:
        z = np.zeros(0, np.int64)
        return z, z, z
    return np.concatenate(out_l), np.concatenate(out_f), np.concatenate(out_k)


def attach_tracks(tracks, n_landmarks: int, base: np.ndarray, match_l, match_f, match_k):
    """Which landmark each new track joins (-1: none, a new landmark) and the observations the map's
    landmarks gain: (track -> landmark, (landmark, frame, keypoint) of the attached observations, one per
    landmark and frame, direct matches first). ``base``: the first global keypoint id of each frame."""
    n_kp = int(base[-1])
    lm_of_kp = np.full(n_kp, -1, np.int64)
    lm_of_kp[base[match_f] + match_k] = match_l
    gk = base[tracks.frame_idx] + tracks.keypoint_idx
    votes = lm_of_kp[gk]
    tid = tracks.track_of_obs
    has = votes >= 0
    joined = np.full(len(tracks), -1, np.int64)
    if has.any():  # the majority landmark of each track with votes
        pairs, counts = np.unique(np.stack([tid[has], votes[has]], 1), axis=0, return_counts=True)
        o = np.lexsort((-counts, pairs[:, 0]))
        pairs = pairs[o]
        first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
        joined[pairs[first, 0]] = pairs[first, 1]
    # candidates: direct matches (priority 0), then the observations of joined tracks (priority 1)
    tl = joined[tid]
    via = tl >= 0
    cand_l = np.concatenate([match_l, tl[via]])
    cand_f = np.concatenate([match_f, tracks.frame_idx[via]])
    cand_k = np.concatenate([match_k, tracks.keypoint_idx[via]])
    prio = np.concatenate([np.zeros(len(match_l), np.int64), np.ones(int(via.sum()), np.int64)])
    cand_g = base[cand_f] + cand_k
    # a keypoint joins the landmark it was matched to directly, else its track's
    direct = lm_of_kp[cand_g]
    keep = (direct < 0) | (direct == cand_l)
    cand_l, cand_f, cand_k, prio, cand_g = cand_l[keep], cand_f[keep], cand_k[keep], prio[keep], cand_g[keep]
    # one observation per (landmark, frame) and one landmark per keypoint
    o = np.lexsort((prio, cand_f, cand_l))
    cand_l, cand_f, cand_k, cand_g = cand_l[o], cand_f[o], cand_k[o], cand_g[o]
    first = np.r_[True, (cand_l[1:] != cand_l[:-1]) | (cand_f[1:] != cand_f[:-1])] if len(o) else np.zeros(0, bool)
    cand_l, cand_f, cand_k, cand_g = cand_l[first], cand_f[first], cand_k[first], cand_g[first]
    _, uk = np.unique(cand_g, return_index=True)
    uk = np.sort(uk)
    return joined, (cand_l[uk], cand_f[uk], cand_k[uk])
