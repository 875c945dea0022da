"""Extending a map with a new posed capture, without building it again.

``extend_map(map, sequence, out, config)`` adds the frames of ``sequence`` to the map at ``map``:

1. the new frames' features are extracted with the map's extractor settings (its provenance's build
   config) and tracked among themselves as a build tracks them (:func:`favormap.build.track_frames`);
2. every landmark visible from a new frame (in the image, within its trained distance range and within
   ``view_cone_deg`` of its viewing cone) takes the keypoint within ``match_radius_px`` of its projection
   (default: the epipolar limit of the map's tracking) whose descriptor is most similar to the landmark's
   (its mean descriptor, or the one its grids render towards the new camera), above ``min_similarity``;
   each keypoint goes to one landmark at most;
3. a new track with such a keypoint joins that landmark (its majority, if several); the landmarks that
   gained observations are triangulated again from all their observations (observations that no longer
   fit are dropped; a landmark whose new observations all fail keeps what it had), and the other new
   tracks are triangulated into new landmarks; the extended map keeps the landmarks a build would keep
   within its landmark budget (``max_landmarks``: the longest tracks, grown ones counted as grown, among
   the map's landmarks and the new ones, then the best remaining tracks of frames that see fewer than the
   map's ``min_frame_landmarks``), so it holds as many landmarks as a build of all its frames;
4. a grown landmark whose grids already render what the new frames saw of it (each new observation's
   keypoint descriptor as close to the rendering towards its frame as the landmark's training patches were
   to theirs) keeps them; the other grown landmarks' grids are fine-tuned and the new landmarks' trained, in
   one training (:func:`favormap.voxels.batches.train_batches`, the map's voxel settings): a grown landmark trains on
   the patches of its new observations, sampled from the new frames, and on those of its existing
   observations as its current grids render them (the rays of the existing frames' patch pixels), and Adam
   starts from its current grids; so the mapping images need not be at hand, and the result stays close
   to the current grids where the new frames add nothing;
5. frames, cameras, tracks, view cones, provenance and the datasets' checksums are written as a new map
   (atomically: :class:`favormap.mapfile.MapWriter`); the input map is never written to.

The stages above are used by the extension only and share its intermediate arrays, so they are kept in
one module (over 450 lines) instead of spread over modules that nothing else imports.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .extend_config import ExtendConfig

__all__ = ["ExtendConfig", "ExtendSummary", "extend_map", "map_build_config"]


@dataclass
class ExtendSummary:
    """What :func:`extend_map` did."""

    output: Path
    frames_before: int
    frames_added: int
    landmarks_before: int
    landmarks_grown: int  # existing landmarks that gained observations
    landmarks_retrained: int  # grown landmarks whose grids were trained again (the others render what they see)
    observations_added: int  # new observations of existing landmarks
    landmarks_added: int  # new landmarks from the new frames' own tracks
    landmarks_removed: int  # the map's landmarks left out of the landmark budget (ExtendConfig.max_landmarks)
    landmarks_after: int
    transform: list | None = None  # the new_to_map similarity applied (None: none)
    alignment: dict | None = None  # the estimated alignment (ExtendConfig.align)
    timings: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["output"] = str(self.output)
        return d


def map_build_config(provenance: dict):
    """The :class:`~favormap.build.BuildConfig` a map was built with (its provenance's ``config``)."""
    from ..build_config import BuildConfig
    from ..voxels.config import VoxelConfig

    cfg = dict((provenance or {}).get("config") or {})
    if not cfg or "extractor" not in cfg:
        raise InputError(
            "the map records no build configuration in its provenance (a merged map?): it cannot be extended"
        )
    names = {f.name for f in dataclasses.fields(BuildConfig)}
    vox_names = {f.name for f in dataclasses.fields(VoxelConfig)}
    vox = VoxelConfig(**{k: v for k, v in (cfg.pop("voxel", None) or {}).items() if k in vox_names})
    return BuildConfig(**{k: v for k, v in cfg.items() if k in names}, voxel=vox)


def _check_config(config: ExtendConfig) -> None:
    if not (config.view_cone_deg >= 0 and np.isfinite(config.view_cone_deg)):
        raise InputError(f"view cone must be a finite number of degrees >= 0, not {config.view_cone_deg}")
    if config.match_radius_px is not None and not (config.match_radius_px > 0 and np.isfinite(config.match_radius_px)):
        raise InputError(f"match radius must be > 0 px, not {config.match_radius_px}")
    if config.min_similarity is not None and not -1 <= config.min_similarity <= 1:
        raise InputError(f"min similarity must be in [-1, 1], not {config.min_similarity}")
    if config.max_landmarks is not None and config.max_landmarks < 1:
        raise InputError(f"max landmarks must be >= 1, not {config.max_landmarks}")
    if config.align and config.transform is not None:
        raise InputError("align and transform exclude each other")


def _similarity(transform) -> np.ndarray:
    """``transform`` as a 4x4 similarity matrix; InputError when it is not one."""
    T = np.asarray(transform, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(f"the transform must be a finite 4x4 matrix, got shape {T.shape}")
    det = float(np.linalg.det(T[:3, :3]))
    if det <= 0:
        raise InputError(f"the transform's 3x3 block is not a scaled rotation (determinant {det:.4g})")
    s = det ** (1 / 3)
    R = T[:3, :3] / s
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError("the transform is not a similarity (s R | t)")
    return T


def moved_sequence(seq, transform):
    """``seq`` with its poses moved by the similarity ``transform`` (x_map = s R x_seq + t): each
    ``cam_from_world`` becomes ``cam_from_world @ transform^-1``, its rows scaled by s to stay rigid."""
    from ..geometry import move_poses

    T = _similarity(transform)
    moved = move_poses(np.stack([fr.cam_from_world for fr in seq.frames]), T)
    frames = [dataclasses.replace(fr, cam_from_world=P) for fr, P in zip(seq.frames, moved)]
    return dataclasses.replace(seq, frames=frames)


def _read_sequence(sequence, fmt):
    from ..io import Sequence, read_sequence

    if isinstance(sequence, Sequence):
        return sequence
    return read_sequence(sequence, fmt)


def extend_map(map_path, sequence, output, config: ExtendConfig | None = None, progress=None) -> ExtendSummary:
    """Add the posed frames of ``sequence`` (a folder, or a :class:`~favormap.io.Sequence`) to the map
    at ``map_path`` and write the result to ``output`` (atomically; ``output`` may not be the input).
    ``progress(stage, done, total)`` reports progress. See the module docstring for the steps."""
    from ..mapfile import Map
    from ..mapfile.writer import check_output_path

    config = ExtendConfig() if config is None else config
    _check_config(config)
    map_path = Path(map_path)
    src = sequence if isinstance(sequence, (str, Path)) else None
    check_output_path(output, [map_path, src])  # before any work
    if not map_path.exists():
        raise InputError(f"map not found: {map_path}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    with Map.open(map_path) as mp:
        build_cfg = map_build_config(mp.provenance)
        seq = _read_sequence(sequence, config.format)  # a bad sequence fails before the map is read
        m = mp.load()
    timings["load"] = round(time.perf_counter() - t0, 3)
    transform, alignment = config.transform, None
    if config.align:
        t = time.perf_counter()
        alignment = _align(map_path, seq, build_cfg, config)
        transform = alignment["b_to_a"]
        timings["align"] = round(time.perf_counter() - t, 3)
    if transform is not None:
        seq = moved_sequence(seq, transform)
    summary = _extend(m, seq, Path(output), build_cfg, config, progress, timings)
    summary.transform = None if transform is None else np.asarray(transform, np.float64).tolist()
    summary.alignment = alignment
    if alignment is not None:
        summary.warnings += [f"alignment: {w}" for w in alignment["warnings"]]
    return summary


def _align(map_path: Path, seq, build_cfg, config: ExtendConfig) -> dict:
    """The similarity new_to_map from a quick map of ``seq`` aligned to the map (favormap.ops.align)."""
    from ..build import build_map
    from ..mapfile import write_map
    from ..voxels.config import VoxelConfig
    from .align import align_maps

    quick = dataclasses.replace(build_cfg, voxel=VoxelConfig.preset("quick"), align_patches=0, refine_window=0)
    m = build_map(seq, quick, device=config.device)
    with tempfile.TemporaryDirectory(prefix="favormap-extend-") as tmp:
        path = Path(tmp) / "new.h5"
        write_map(m, path)
        return align_maps(map_path, path).to_dict()


# -------------------------------------------------------------------------------------------------
# matching the new frames to the map's landmarks
# -------------------------------------------------------------------------------------------------
def _unit(x) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def match_radius(m, cfg, config: ExtendConfig) -> float:
    """The projection matching radius (px): ExtendConfig's, else the epipolar limit of the map's tracking
    (its build config's, else the one its build measured), else the extractor's keypoint precision."""
    from ..build_config import default_max_epipolar

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
    from ..geometry import camera_centers, project
    from ..localize.matching import radius_pairs
    from ..visibility import ViewLimits, visible_mask
    from ..voxels.render_numpy import render_from_camera_numpy

    limits = ViewLimits(angle_margin_deg=config.view_cone_deg)
    mean_desc = _unit(m.mean_descriptor)
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
        R3 = m.grid_resolution**3
        rendered = _unit(
            render_from_camera_numpy(
                np.asarray(m.descriptors[rows], np.float32).reshape(len(rows), R3, -1),
                np.asarray(m.density[rows], np.float32).reshape(len(rows), R3),
                np.asarray(m.positions[rows], np.float32),
                np.asarray(m.voxel_size[rows], np.float32),
                np.asarray(camera_centers(T), np.float32),
                m.render_samples,
            )
        )
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


# -------------------------------------------------------------------------------------------------
# the extension
# -------------------------------------------------------------------------------------------------
def within_budget(m, glms, grown_rows: np.ndarray, nlms, budget: int, min_frame_landmarks: int, M0: int):
    """The landmarks of the extended map within ``budget``, chosen as a build chooses them
    (:func:`favormap.build.landmark_budget`: the longest tracks, then the lowest mean reprojection error,
    then the best remaining tracks of frames that see fewer than ``min_frame_landmarks``) among the map's
    untouched landmarks, the grown ones (their tracks as grown) and the new ones (of new frames, numbered
    from ``M0``).

    Returns the grown landmarks kept (and their map rows), the new ones kept, and the sorted rows of the
    map's landmarks left out (untouched or grown)."""
    from ..build import landmark_budget

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
    from ..geometry import camera_centers
    from ..voxels.render_numpy import render_from_camera_numpy

    tr = glms.tracks
    new = np.flatnonzero(tr.frame_idx >= M0)
    j, f, k = tr.track_of_obs[new], tr.frame_idx[new] - M0, tr.keypoint_idx[new]
    rows = grown_rows[j]
    R3 = m.grid_resolution**3
    ok = np.zeros(len(new), bool)
    order = np.argsort(f, kind="stable")
    bounds = np.searchsorted(f[order], np.arange(len(ff.features) + 1))
    for frame in range(len(ff.features)):
        sel = order[bounds[frame] : bounds[frame + 1]]
        if not len(sel):
            continue
        r = rows[sel]
        rendered = render_from_camera_numpy(
            np.asarray(m.descriptors[r], np.float32).reshape(len(r), R3, -1),
            np.asarray(m.density[r], np.float32).reshape(len(r), R3),
            np.asarray(m.positions[r], np.float32),
            np.asarray(m.voxel_size[r], np.float32),
            np.asarray(camera_centers(ff.cam_from_world[frame]), np.float32),
            m.render_samples,
        )
        seen = _unit(np.asarray(ff.features[frame].descriptors, np.float32)[k[sel]])
        ok[sel] = np.einsum("ij,ij->i", rendered, seen) >= np.asarray(m.cosine, np.float32)[r]
    return np.bincount(j[~ok], minlength=len(glms)) > 0


class _Stages:
    def __init__(self, timings: dict, progress):
        self.timings, self.progress = timings, progress or (lambda *a: None)

    def __call__(self, name):
        return _Stage(self, name)


class _Stage:
    def __init__(self, owner, name):
        self.owner, self.name = owner, name

    def __enter__(self):
        self.t = time.perf_counter()

    def __exit__(self, *exc):
        self.owner.timings[self.name] = round(time.perf_counter() - self.t, 3)
        self.owner.progress(self.name, 1, 1)


def _frames_and_cameras(m, seq):
    """The output's cameras (equal cameras shared), frame names (new names that collide prefixed
    ``+N/``), frame camera ids and poses."""
    from .merge import _camera_id

    cameras = dict(m.cameras)
    new_ids = {cid: _camera_id(cameras, cam) for cid, cam in seq.cameras.items()}
    names = list(m.frame_names)
    seen = set(names)
    for fr in seq.frames:
        name, k = fr.name, 1
        while name in seen:
            name, k = f"+{k}/{fr.name}", k + 1
        seen.add(name)
        names.append(name)
    cam_ids = np.concatenate([np.asarray(m.frame_camera_ids, np.int32), [new_ids[f.camera_id] for f in seq.frames]])
    poses = np.concatenate([np.asarray(m.cam_from_world, np.float64), np.stack([f.cam_from_world for f in seq.frames])])
    return cameras, names, cam_ids.astype(np.int32), poses


def frames_in_map(m, seq) -> list[str]:
    """Names of the frames of ``seq`` that the map ``m`` holds already: the same name and the same pose."""
    index = {name: i for i, name in enumerate(m.frame_names)}
    poses = np.asarray(m.cam_from_world, np.float64)
    return [
        f.name
        for f in seq.frames
        if f.name in index and np.allclose(poses[index[f.name]], f.cam_from_world, rtol=1e-5, atol=1e-6)
    ]


def _extend(m, seq, output: Path, cfg, config: ExtendConfig, progress, timings: dict) -> ExtendSummary:
    from ..build import (
        ExtractorSpec,
        check_build_input,
        extract_sequence,
        landmark_geometry,
        track_frames,
        track_mean_descriptors,
        triangulate_tracks,
    )
    from ..build_config import localize_defaults
    from ..io import working_camera
    from ..mapfile import write_map
    from ..mapfile.model import MapData, median_landmark_reproj_error, new_landmark_ids
    from ..tracking import Tracks
    from ..triangulation import TriangulationConfig, triangulate
    from ..voxels.batches import train_batches

    check_build_input(seq, cfg)
    if cfg.max_side != m.max_side or cfg.extractor != m.extractor:
        raise InputError("the map's build configuration does not match the map (max_side, extractor)")
    stage = _Stages(timings, progress)
    warnings: list[str] = []
    again = frames_in_map(m, seq)
    if again:
        warnings.append(
            f"{len(again)} of the {len(seq.frames)} new frames are in the map already (the same name and pose, "
            f"e.g. {again[0]}): they are added again and their observations count twice"
        )
    if cfg.refine_poses:
        warnings.append(
            "the map's poses were refined by bundle adjustment (build --refine-poses) and the new frames' are "
            "used as given: landmarks seen from both agree only as well as the given poses do"
        )
    L0, M0 = m.num_landmarks, m.num_frames
    extractor = ExtractorSpec(cfg.extractor, cfg.max_keypoints)
    with stage("extract"):
        ff = extract_sequence(seq, extractor, cfg.max_side, progress)
    with stage("track"):
        tracks = track_frames(ff, cfg)
    with stage("match"):
        min_sim = cfg.min_similarity if config.min_similarity is None else config.min_similarity
        radius = match_radius(m, cfg, config)
        match_l, match_f, match_k = match_landmarks(m, ff, config, min_sim, radius)
        counts = np.array([len(f.keypoints) for f in ff.features], np.int64)
        base = np.concatenate([[0], np.cumsum(counts)])
        joined, (add_l, add_f, add_k) = attach_tracks(tracks, L0, base, match_l, match_f, match_k)

    # -- triangulation: grown landmarks from all their observations, new ones from the free tracks -------
    cameras, names, cam_ids, poses = _frames_and_cameras(m, seq)
    Ks_old = {cid: working_camera(cam, m.max_side).K for cid, cam in m.cameras.items()}
    Ks = np.concatenate([np.stack([Ks_old[int(c)] for c in m.frame_camera_ids]), np.stack([c.K for c in ff.cameras])])
    tri_cfg = TriangulationConfig(cfg.max_reproj_px, cfg.min_angle_deg, min_track=cfg.min_track)
    with stage("triangulate"):
        grown = np.unique(add_l)
        old_tl, old_tf, old_xy = np.asarray(m.track_landmark), np.asarray(m.track_frame), np.asarray(m.track_xy)
        slot = np.full(L0, -1, np.int64)
        slot[grown] = np.arange(len(grown))
        old_sel = np.flatnonzero(slot[old_tl] >= 0)
        new_xy = np.concatenate(
            [np.asarray(ff.features[f].keypoints, np.float64)[add_k[add_f == f]] for f in range(len(ff.features))]
            or [np.zeros((0, 2))]
        )
        order = np.argsort(add_f, kind="stable")  # new_xy is by frame
        add_l, add_f, add_k = add_l[order], add_f[order], add_k[order]
        # old observations carry their observation row in keypoint_idx (their patches are copied from it)
        gt = Tracks.from_obs(
            np.concatenate([old_tf[old_sel], add_f + M0]),
            np.concatenate([old_sel, add_k]),
            np.concatenate([old_xy[old_sel].astype(np.float64), new_xy]),
            np.concatenate([slot[old_tl[old_sel]], slot[add_l]]),
        )
        glms = triangulate(gt, poses, Ks, tri_cfg) if len(gt) else None
        if glms is not None and len(glms):
            # a landmark stays grown only while some of its new observations fit
            new_obs = glms.tracks.frame_idx >= M0
            has_new = np.bincount(glms.tracks.track_of_obs[new_obs], minlength=len(glms)) > 0
            glms = glms.select(np.flatnonzero(has_new))
            grown_rows = grown[glms.source]
        else:
            glms, grown_rows = None, np.zeros(0, np.int64)
        free = np.flatnonzero(joined < 0)
        keep_obs = np.isin(tracks.track_of_obs, free)
        ntr = tracks.select(keep_obs)
        nlms = triangulate_tracks(ntr, ff, cfg) if len(ntr) else None
        nlms = nlms if nlms is not None and len(nlms) else None
        budget = cfg.max_landmarks if config.max_landmarks is None else config.max_landmarks
        glms, grown_rows, nlms, dropped = within_budget(m, glms, grown_rows, nlms, budget, cfg.min_frame_landmarks, M0)
    n_grown = 0 if glms is None else len(glms)
    n_new = 0 if nlms is None else len(nlms)
    n_added_obs = 0 if glms is None else int((glms.tracks.frame_idx >= M0).sum())

    # -- training: the grown landmarks fine-tuned, the new ones trained -----------------------------------
    with stage("train"):
        # a grown landmark whose grids already render what the new frames see of it keeps them
        retrain = unexplained(m, glms, grown_rows, M0, ff) if n_grown else np.zeros(0, bool)
        gtrain = glms.select(np.flatnonzero(retrain)) if retrain.any() else None
        upd = _training_set(m, gtrain, grown_rows[retrain], nlms, M0, ff, poses, Ks, cfg, extractor)
        grids = train_batches(upd.rays, cfg.voxel, cfg.train_batch) if upd is not None else None
    n_retrained = int(retrain.sum())
    # -- the output map ---------------------------------------------------------------------------
    with stage("write"):
        U = n_grown + n_new
        lm_rows = np.concatenate([grown_rows, np.arange(L0, L0 + n_new)]).astype(np.int64)
        trained = np.concatenate([grown_rows[retrain], np.arange(L0, L0 + n_new)]).astype(np.int64)
        T = len(trained)
        all_lms = _concat_landmarks(glms, nlms, M0)
        arrays = {k: np.array(getattr(m, k)) for k in MapData.landmark_names()}
        for k in list(arrays):
            if k in ("descriptors", "density"):
                continue
            if n_new:
                arrays[k] = np.concatenate([arrays[k], np.zeros((n_new,) + arrays[k].shape[1:], arrays[k].dtype)])
        R = m.grid_resolution
        desc = np.concatenate([m.descriptors, np.zeros((n_new, R, R, R, m.channels), np.float32)])
        dens = np.concatenate([m.density, np.zeros((n_new, R, R, R), np.float32)])
        if U:
            arrays["ids"][L0:] = new_landmark_ids(n_new, avoid=arrays["ids"][:L0])
            arrays["positions"][lm_rows] = all_lms.positions
            arrays["track_length"][lm_rows] = all_lms.tracks.lengths
            arrays["reproj_error"][lm_rows] = all_lms.mean_reproj_error
            vd, va, dr = landmark_geometry(all_lms, poses)
            arrays["view_dir"][lm_rows], arrays["view_angle"][lm_rows], arrays["depth_range"][lm_rows] = vd, va, dr
        if T:  # the trained landmarks' grids (the grown ones that kept theirs keep their voxel fields)
            arrays["voxel_size"][trained] = upd.rays.sizes
            arrays["quality"][trained] = grids.psnr
            arrays["cosine"][trained] = grids.cosine
            arrays["mean_descriptor"][trained] = track_mean_descriptors(
                upd.rays, T, cfg.voxel.patch_size, cfg.voxel.mean_patch, cfg.voxel.patch_stride
            )
            desc[trained] = grids.descriptors.cpu().numpy().reshape(T, R, R, R, -1)
            dens[trained] = grids.density.cpu().numpy().reshape(T, R, R, R)
        arrays["descriptors"], arrays["density"] = desc, dens
        # observations: the untouched landmarks' as they were, then the updated landmarks'
        touched = np.zeros(L0 + n_new, bool)
        touched[lm_rows] = True
        keep_old = ~touched[old_tl]
        tl = np.concatenate([old_tl[keep_old], lm_rows[all_lms.tracks.track_of_obs]]).astype(np.int32)
        tf = np.concatenate([old_tf[keep_old], all_lms.tracks.frame_idx]).astype(np.int32)
        txy = np.concatenate([old_xy[keep_old], all_lms.tracks.xy]).astype(np.float32)
        patches = None
        if m.track_patch is not None:
            patches = _patches(m, keep_old, all_lms, M0, seq, ff, cfg)
        if len(dropped):  # the map's landmarks left out of the budget, with their observations
            kept = np.ones(L0 + n_new, bool)
            kept[dropped] = False
            obs_kept = kept[tl]
            tl, tf, txy = (np.cumsum(kept) - 1)[tl[obs_kept]].astype(np.int32), tf[obs_kept], txy[obs_kept]
            patches = None if patches is None else patches[obs_kept]
            arrays = {k: v[kept] for k, v in arrays.items()}
        o = np.argsort(tl, kind="stable")
        kw, extra = MapData.split_landmark_arrays(arrays)
        stats = dict(m.provenance.get("stats") or {})
        stats.update(
            frames=len(names),
            landmarks=int(L0 + n_new - len(dropped)),
            mean_track_length=float(np.mean(arrays["track_length"])) if len(arrays["ids"]) else 0.0,
            median_reproj_error_px=median_landmark_reproj_error(
                arrays["reproj_error"].astype(np.float32), arrays["track_length"]
            ),
            median_psnr=float(np.median(arrays["quality"])) if len(arrays["ids"]) else float("nan"),
        )
        record = {
            "source_map": str(m.provenance.get("source_map_path", "")) or None,
            "sequence": str(seq.root),
            "sequence_format": seq.format,
            "frames_before": M0,
            "frames_added": len(seq.frames),
            "landmarks_before": L0,
            "landmarks_grown": n_grown,
            "landmarks_retrained": n_retrained,
            "observations_added": n_added_obs,
            "landmarks_added": n_new,
            "landmarks_removed": len(dropped),
            "view_cone_deg": config.view_cone_deg,
            "match_radius_px": radius,
            "min_similarity": float(min_sim),
            "timings": timings,
        }
        provenance = dict(m.provenance)
        provenance.update(
            operation="extend",
            stats=stats,
            localize_defaults=m.provenance.get("localize_defaults", localize_defaults(cfg)),
            extensions=[*m.provenance.get("extensions", []), record],
        )
        provenance.pop("source_map_path", None)
        out = MapData(
            extractor=m.extractor,
            channels=m.channels,
            grid_resolution=R,
            patch_size=m.patch_size,
            render_samples=m.render_samples,
            max_side=m.max_side,
            cameras=cameras,
            frame_names=names,
            frame_camera_ids=cam_ids,
            cam_from_world=poses,
            track_landmark=tl[o],
            track_frame=tf[o],
            track_xy=txy[o],
            track_patch=None if patches is None else patches[o],
            provenance=provenance,
            extra=extra,
            **kw,
        )
        write_map(out, output)
    return ExtendSummary(
        output=output,
        frames_before=M0,
        frames_added=len(seq.frames),
        landmarks_before=L0,
        landmarks_grown=n_grown,
        landmarks_retrained=n_retrained,
        observations_added=n_added_obs,
        landmarks_added=n_new,
        landmarks_removed=len(dropped),
        landmarks_after=L0 + n_new - len(dropped),
        timings=timings,
        warnings=warnings,
    )


def _concat_landmarks(glms, nlms, M0: int):
    """The grown landmarks (frames of the whole map) and the new ones (new frames, shifted by ``M0``)
    as one Landmarks over all frames."""
    from ..tracking import Tracks
    from ..triangulation import Landmarks

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


def _patches(m, keep_old, all_lms, M0: int, seq, ff, cfg) -> np.ndarray:
    """The stored observation pixels (tracks/patch) of the output's observations, in the order
    ``_extend`` lists them: the untouched landmarks' as stored, then the updated landmarks' (existing
    observations: as stored, found by their row; new ones: cut from the new frames' images)."""
    from ..build import observation_patches
    from ..tracking import Tracks
    from ..triangulation import Landmarks

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


@dataclass
class _Update:
    rays: object  # TrainingRays of the grown, then the new landmarks


def _training_set(m, glms, grown_rows, nlms, M0, ff, poses, Ks, cfg, extractor):
    """The training rays of the landmarks to train: the grown ones (their new observations' sampled
    patches, their existing observations' patches rendered from their current grids, Adam starting from
    those grids), then the new ones (their sampled patches)."""
    import torch

    from ..build import training_rays
    from ..tracking import Tracks
    from ..triangulation import Landmarks
    from ..voxels.config import TrainingRays
    from ..voxels.rays import patch_rays, voxel_sizes
    from ..voxels.train import render_training_rays

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
        R3 = m.grid_resolution**3
        with torch.no_grad():
            rendered = render_training_rays(
                render_data,
                torch.as_tensor(np.asarray(m.descriptors[ur], np.float32).reshape(len(ur), R3, -1)),
                torch.as_tensor(np.asarray(m.density[ur], np.float32).reshape(len(ur), R3)),
                v,
            ).numpy()
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
        init_d[: len(glms)] = np.asarray(m.descriptors[grown_rows], np.float32).reshape(len(glms), R3, -1)
        init_s[: len(glms)] = np.asarray(m.density[grown_rows], np.float32).reshape(len(glms), R3)
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
