"""The extended map assembled (step 5): the map's arrays with the grown landmarks updated and the new ones
appended, the landmarks left out of the budget removed, the observations, the provenance."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .frames import Frames
from .matching import NewFrames
from .training import Trained
from .triangulate import Grown, concat_landmarks

if TYPE_CHECKING:
    from ...mapfile.model import MapData
    from ...triangulation import Landmarks

_GRIDS = ("descriptors", "density")


@dataclass
class Observations:
    """The extended map's observations (tracks/*), one row each."""

    landmark: np.ndarray  # (O,) int32 landmark row
    frame: np.ndarray  # (O,) int32 frame
    xy: np.ndarray  # (O, 2) float32 keypoint
    patch: np.ndarray | None  # (O, P, P) uint8 stored pixels (None: the map stores none)

    def of_kept(self, kept: np.ndarray) -> Observations:
        """The observations of the ``kept`` landmarks (bool over the landmark rows), renumbered."""
        obs_kept = kept[self.landmark]
        return Observations(
            (np.cumsum(kept) - 1)[self.landmark[obs_kept]].astype(np.int32),
            self.frame[obs_kept],
            self.xy[obs_kept],
            None if self.patch is None else self.patch[obs_kept],
        )


def assemble_map(m, seq, new: NewFrames, frames: Frames, lms: Grown, trained: Trained, cfg, record: dict) -> MapData:
    """The extended map: the map ``m``'s landmarks, the grown ones updated (``lms``; retrained ones with their
    new grids, ``trained``), the new ones appended, those out of the budget removed with their observations;
    the frames ``frames``; the provenance with ``record`` appended to its ``extensions``."""
    from ...mapfile.model import MapData

    L0, M0, n_new = m.num_landmarks, m.num_frames, lms.n_new
    lm_rows = np.concatenate([lms.grown_rows, np.arange(L0, L0 + n_new)]).astype(np.int64)
    all_lms = concat_landmarks(lms.grown, lms.new, M0)
    arrays = _landmark_arrays(m, lms, trained, all_lms, lm_rows, frames, cfg)
    obs = _observations(m, all_lms, lm_rows, n_new, seq, new.ff, cfg)
    if len(lms.dropped):  # the map's landmarks left out of the budget, with their observations
        kept = np.ones(L0 + n_new, bool)
        kept[lms.dropped] = False
        obs = obs.of_kept(kept)
        arrays = {k: v[kept] for k, v in arrays.items()}
    o = np.argsort(obs.landmark, kind="stable")
    kw, extra = MapData.split_landmark_arrays(arrays)
    return MapData(
        extractor=m.extractor,
        channels=m.channels,
        grid_resolution=m.grid_resolution,
        patch_size=m.patch_size,
        render_samples=m.render_samples,
        max_side=m.max_side,
        cameras=frames.cameras,
        frame_names=frames.names,
        frame_camera_ids=frames.camera_ids,
        cam_from_world=frames.cam_from_world,
        track_landmark=obs.landmark[o],
        track_frame=obs.frame[o],
        track_xy=obs.xy[o],
        track_patch=None if obs.patch is None else obs.patch[o],
        cam_from_rig=m.cam_from_rig,
        provenance=_provenance(m, arrays, len(frames.names), cfg, record),
        extra=extra,
        **kw,
    )


def _landmark_arrays(
    m, lms: Grown, trained: Trained, all_lms: Landmarks, lm_rows: np.ndarray, frames: Frames, cfg
) -> dict[str, np.ndarray]:
    """The map's per-landmark arrays with the new landmarks appended (rows from L0): the updated landmarks
    (rows ``lm_rows``: the grown, then the new ones, ``all_lms``) with their positions, tracks and view
    geometry, the trained ones with their grids."""
    from ...build import landmark_geometry, track_mean_descriptors
    from ...mapfile.model import MapData, new_landmark_ids

    L0, n_new, R = m.num_landmarks, lms.n_new, m.grid_resolution
    arrays = {k: getattr(m, k) if k in _GRIDS else np.array(getattr(m, k)) for k in MapData.landmark_names()}
    for k in arrays:
        if n_new and k not in _GRIDS:
            arrays[k] = np.concatenate([arrays[k], np.zeros((n_new,) + arrays[k].shape[1:], arrays[k].dtype)])
    desc = np.concatenate([m.descriptors, np.zeros((n_new, R, R, R, m.channels), np.float32)])
    dens = np.concatenate([m.density, np.zeros((n_new, R, R, R), np.float32)])
    if len(lm_rows):
        arrays["ids"][L0:] = new_landmark_ids(n_new, avoid=arrays["ids"][:L0])
        arrays["positions"][lm_rows] = all_lms.positions
        arrays["track_length"][lm_rows] = all_lms.tracks.lengths
        arrays["reproj_error"][lm_rows] = all_lms.mean_reproj_error
        vd, va, dr = landmark_geometry(all_lms, frames.cam_from_world)
        arrays["view_dir"][lm_rows], arrays["view_angle"][lm_rows], arrays["depth_range"][lm_rows] = vd, va, dr
    # the trained landmarks' grids (the grown ones that kept theirs keep their voxel fields)
    rows = np.concatenate([lms.grown_rows[trained.retrain], np.arange(L0, L0 + n_new)]).astype(np.int64)
    T = len(rows)
    if T:
        rays, grids, v = trained.rays, trained.grids, cfg.voxel
        arrays["voxel_size"][rows] = rays.sizes
        arrays["quality"][rows] = grids.psnr
        arrays["cosine"][rows] = grids.cosine
        arrays["mean_descriptor"][rows] = track_mean_descriptors(rays, T, v.patch_size, v.mean_patch, v.patch_stride)
        desc[rows] = grids.descriptors.cpu().numpy().reshape(T, R, R, R, -1)
        dens[rows] = grids.density.cpu().numpy().reshape(T, R, R, R)
    arrays["descriptors"], arrays["density"] = desc, dens
    return arrays


def _observations(m, all_lms: Landmarks, lm_rows: np.ndarray, n_new: int, seq, ff, cfg) -> Observations:
    """The extended map's observations, before the budget: the untouched landmarks' as they were, then the
    updated landmarks' (rows ``lm_rows``, observations ``all_lms``)."""
    L0, M0 = m.num_landmarks, m.num_frames
    old_tl, old_tf, old_xy = np.asarray(m.track_landmark), np.asarray(m.track_frame), np.asarray(m.track_xy)
    touched = np.zeros(L0 + n_new, bool)
    touched[lm_rows] = True
    keep_old = ~touched[old_tl]
    return Observations(
        np.concatenate([old_tl[keep_old], lm_rows[all_lms.tracks.track_of_obs]]).astype(np.int32),
        np.concatenate([old_tf[keep_old], all_lms.tracks.frame_idx]).astype(np.int32),
        np.concatenate([old_xy[keep_old], all_lms.tracks.xy]).astype(np.float32),
        None if m.track_patch is None else _patches(m, keep_old, all_lms, M0, seq, ff, cfg),
    )


def _provenance(m, arrays: dict[str, np.ndarray], n_frames: int, cfg, record: dict) -> dict:
    """The map's provenance as the extension leaves it: operation ``extend``, the stats of the extended map
    (``arrays``, ``n_frames``), ``record`` appended to the extensions."""
    from ...build_config import localize_defaults
    from ...mapfile.model import median_landmark_reproj_error

    n = len(arrays["ids"])
    stats = dict(m.provenance.get("stats") or {})
    stats.update(
        frames=n_frames,
        landmarks=int(n),
        mean_track_length=float(np.mean(arrays["track_length"])) if n else 0.0,
        median_reproj_error_px=median_landmark_reproj_error(
            arrays["reproj_error"].astype(np.float32), arrays["track_length"]
        ),
        median_psnr=float(np.median(arrays["quality"])) if n else float("nan"),
    )
    provenance = dict(m.provenance)
    provenance.update(
        operation="extend",
        stats=stats,
        localize_defaults=m.provenance.get("localize_defaults", localize_defaults(cfg)),
        extensions=[*m.provenance.get("extensions", []), record],
    )
    provenance.pop("source_map_path", None)
    return provenance


def _patches(m, keep_old, all_lms, M0: int, seq, ff, cfg) -> np.ndarray:
    """The stored observation pixels (tracks/patch) of the output's observations, in the order
    :func:`_observations` lists them: the untouched landmarks' as stored, then the updated landmarks' (existing
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
