"""The stages of the extension, from the new frames' features to the written map."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..extend_config import ExtendConfig
from .api import ExtendSummary
from .assemble import _patches
from .budget import unexplained, within_budget
from .matching import attach_tracks, match_landmarks, match_radius
from .training import _concat_landmarks, _training_set


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
    from ..merge import _camera_id

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
    from ...build import (
        ExtractorSpec,
        check_build_input,
        extract_sequence,
        landmark_geometry,
        track_frames,
        track_mean_descriptors,
        triangulate_tracks,
    )
    from ...build_config import localize_defaults
    from ...io import working_camera
    from ...mapfile import write_map
    from ...mapfile.model import MapData, median_landmark_reproj_error, new_landmark_ids
    from ...tracking import Tracks
    from ...triangulation import TriangulationConfig, triangulate
    from ...voxels.batches import train_batches

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
