"""Merging maps.

``merge_maps(paths, out)`` combines maps built with the same extractor / channels / grid / patch
size into one file without loading their voxel grids into memory: landmark metadata is combined in
memory, voxel grids are copied batch by batch (``Map.voxels`` on row batches) into the output
datasets through :class:`MapWriter`.

Merge rules
-----------
- Later maps may be moved into the first map's frame with a transform ``b_to_a`` (rigid, or a
  similarity s*R|t). Positions, view directions, depth ranges and voxel sizes are mapped exactly;
  frames' ``cam_from_world`` become ``cam_from_world_b @ b_to_a^-1`` (re-scaled to stay rigid).
  Voxel grids are axis-aligned in the world, so a rotation cannot move them exactly: the grid of
  every rotated landmark is *resampled* (same centre and size, nodes of the new axis-aligned grid
  mapped back into the old grid and interpolated trilinearly, clamped to the old cube). This is
  exact for translations, scales and rotations by multiples of 90 degrees about the axes (nodes
  land on nodes), and approximate otherwise: a warning is returned.
- Deduplication: a landmark of a later map closer than the dedup radius (default: the voxel size of
  the existing landmark it is compared with) to an existing landmark, whose mean descriptor has a
  cosine similarity > ``MergeConfig.min_cosine`` with it, is a duplicate. The one with the higher quality (PSNR)
  is kept, the other dropped with its observations. Ties keep the existing landmark, so merging a
  map with itself gives the same landmarks.
- Frames and cameras are concatenated (camera ids renumbered 0..K-1 in source order, cameras equal in
  model, size and parameters shared: maps of one camera give a map of one camera; frame names
  that collide get a ``<source index>/`` prefix); track rows are remapped; landmark ids stay
  unique (ids of later maps that collide are regenerated with ``new_landmark_ids``).
- Provenance lists the sources (path, counts, their provenance) and the merge parameters.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import geometry
from ..errors import IncompatibleMapsError, InputError
from ..io import working_camera
from ..mapfile import Map, new_landmark_ids
from ..mapfile.fields import field_name, metadata_datasets
from ..mapfile.writer import MapWriter, check_output_path
from .merge_config import MergeConfig
from .rewrite import copy_voxels, write_frames_and_tracks, write_landmark_metadata

# attributes that must be equal for maps to be merged
COMPAT_FIELDS = ("extractor", "channels", "grid_resolution", "patch_size")


# -------------------------------------------------------------------------------------------------
# merge
# -------------------------------------------------------------------------------------------------
@dataclass
class MergeResult:
    path: Path
    num_landmarks: int
    num_frames: int
    num_cameras: int
    sources: list = field(default_factory=list)  # per source: path, landmarks, kept, dropped_duplicates, replaced
    ids_regenerated: int = 0
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "output": str(self.path),
            "num_landmarks": self.num_landmarks,
            "num_frames": self.num_frames,
            "num_cameras": self.num_cameras,
            "sources": self.sources,
            "ids_regenerated": self.ids_regenerated,
            "warnings": self.warnings,
        }


def check_compatible(maps: list) -> None:
    a = maps[0]
    for b in maps[1:]:
        for k in COMPAT_FIELDS:
            va, vb = getattr(a, k), getattr(b, k)
            if va != vb:
                raise IncompatibleMapsError(f"cannot merge {a.path} and {b.path}: different {k} ({va!r} vs {vb!r})")
        if not np.allclose(a.cam_from_rig, b.cam_from_rig, atol=1e-9):
            # the frames hold camera poses either way; a merged map reports poses in one convention
            angle = geometry.rotation_angle_deg(a.cam_from_rig[:3, :3].T @ b.cam_from_rig[:3, :3])
            raise IncompatibleMapsError(
                f"cannot merge {a.path} and {b.path}: their cameras are turned differently against the poses "
                f"they were built from (frames/cam_from_rig, {angle:.3g} deg apart)"
            )


def resample_matrix(R_b_to_a: np.ndarray, res: int) -> np.ndarray | None:
    """(R^3, R^3) matrix W with new_nodes = W @ old_nodes for a grid rotated by ``R_b_to_a``
    (None when the rotation is the identity)."""
    if np.allclose(R_b_to_a, np.eye(3), atol=1e-9):
        return None
    import torch

    from ..voxels.render import trilinear_stencil

    g = np.arange(res) / (res - 1)
    u_new = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # (x, y, z) node order
    u_old = (u_new - 0.5) @ R_b_to_a + 0.5  # R^T (u - 0.5) for row vectors
    u_old = np.where(
        np.abs(u_old - np.round(u_old * (res - 1)) / (res - 1)) < 1e-9, np.round(u_old * (res - 1)) / (res - 1), u_old
    )
    W = trilinear_stencil(torch.as_tensor(u_old, dtype=torch.float64), res).numpy()
    return W.astype(np.float32)


def _frame_scale(cameras_b: dict, frame_cam_b: np.ndarray, max_side_b: int, max_side_a: int) -> np.ndarray | None:
    """Per-frame (sx, sy) that converts track pixels at max_side_b into pixels at max_side_a."""
    if max_side_a == max_side_b:
        return None
    ids = sorted(cameras_b)
    f = np.ones((len(ids), 2))
    for i, k in enumerate(ids):
        wb, wa = working_camera(cameras_b[k], max_side_b), working_camera(cameras_b[k], max_side_a)
        f[i] = (wa.width / wb.width, wa.height / wb.height)
    return f[np.searchsorted(ids, frame_cam_b)]


def merge_maps(
    paths,
    out,
    config: MergeConfig | None = None,
    transform: np.ndarray | None = None,
    chunk: int = 4096,
    progress=None,
) -> MergeResult:
    """Merge the maps at ``paths`` into ``out`` (atomic). ``transform``: 4x4 b_to_a (rigid or
    similarity) applied to the second and later maps. See the module docstring for the rules."""
    config = MergeConfig() if config is None else config
    dedup_radius, min_cosine, dedup = config.dedup_radius, config.min_cosine, config.dedup
    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise InputError("merge needs at least two maps")
    check_output_path(out, paths)  # fail before any work
    if dedup_radius is not None and not (dedup_radius >= 0 and np.isfinite(dedup_radius)):
        raise InputError(f"--dedup-radius must be a finite number >= 0, got {dedup_radius}")
    with ExitStack() as stack:
        maps = [stack.enter_context(Map.open(p)) for p in paths]
        check_compatible(maps)
        return _merge(maps, Path(out), dedup_radius, transform, min_cosine, dedup, chunk, progress)


@dataclass
class _Similarity:
    """A transform b_to_a = s*R|t taken apart: ``W`` resamples rotated voxel grids (None: identity)."""

    T: np.ndarray
    scale: float
    R: np.ndarray
    W: np.ndarray | None


def _similarity(transform, res: int, warnings: list) -> _Similarity | None:
    if transform is None:
        return None
    T = np.asarray(transform, np.float64)
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    Rot = T[:3, :3] / scale
    W = resample_matrix(Rot, res)
    ang = float(np.degrees(np.arccos(np.clip((np.trace(Rot) - 1) / 2, -1, 1))))
    exact = W is None or np.allclose(W, np.round(W), atol=1e-6)
    if not exact:
        warnings.append(
            f"the transform rotates by {ang:.2f} deg: voxel grids of the transformed maps were "
            "resampled by trilinear interpolation (approximate)"
        )
    return _Similarity(T, scale, Rot, W)


def _to_first_frame(m, sim: _Similarity | None) -> dict:
    """The landmark metadata of one source by field name, moved by ``sim`` (None: unchanged)."""
    d = {field_name(p): np.asarray(getattr(m, field_name(p))) for p in metadata_datasets()}
    d["ids"] = np.asarray(m.ids, np.uint64)
    if sim is not None:
        d["positions"] = geometry.transform_points(sim.T, d["positions"])
        d["view_dir"] = (d["view_dir"].astype(np.float64) @ sim.R.T).astype(np.float32)
        d["voxel_size"] = (d["voxel_size"] * sim.scale).astype(np.float32)
        d["depth_range"] = (d["depth_range"] * sim.scale).astype(np.float32)
    return d


def _duplicates(maps, meta, k: int, s_all, r_all, dedup_radius, min_cosine):
    """Landmarks of map ``k`` that duplicate an entry (source ``s_all``, row ``r_all``) of the output
    so far: (keep_new mask over map k's rows, output slots to replace, map k's rows replacing them)."""
    from .spatial import SpatialIndex

    mk, dk = maps[k], meta[k]
    keep_new = np.ones(len(mk), bool)
    none = np.zeros(0, np.int64)
    ex_pos = np.concatenate([meta[s]["positions"][r_all[s_all == s]] for s in range(k)])
    order = np.concatenate([np.flatnonzero(s_all == s) for s in range(k)])  # ex_pos rows -> slots
    idx = SpatialIndex(ex_pos, backend="open3d")
    nn, dist = idx.knn_batch(dk["positions"], 8)
    valid = nn >= 0
    slot = np.where(valid, order[np.maximum(nn, 0)], 0)
    ex_src, ex_row = s_all[slot], r_all[slot]
    ex_size = np.zeros(slot.shape, np.float64)
    ex_q = np.zeros(slot.shape, np.float64)
    for s in range(k):
        sel = ex_src == s
        ex_size[sel] = meta[s]["voxel_size"][ex_row[sel]]
        ex_q[sel] = meta[s]["quality"][ex_row[sel]]
    radius = ex_size if dedup_radius is None else np.full(slot.shape, dedup_radius)
    close = valid & (dist <= radius)
    cand_b, cand_j = np.nonzero(close)
    cos = np.zeros(len(cand_b))
    if len(cand_b):
        db = _unit(mk.mean_descriptors(np.unique(cand_b)))
        ub = np.unique(cand_b)
        vb = db[np.searchsorted(ub, cand_b)]
        va = np.zeros_like(vb)
        cs, cr = ex_src[cand_b, cand_j], ex_row[cand_b, cand_j]
        for s in range(k):
            sel = cs == s
            if sel.any():
                ur, inv = np.unique(cr[sel], return_inverse=True)
                va[sel] = _unit(maps[s].mean_descriptors(ur))[inv]
        cos = np.sum(va * vb, 1)
    similar = np.zeros(close.shape, bool)
    similar[cand_b[cos > min_cosine], cand_j[cos > min_cosine]] = True
    has = similar.any(1)
    first_j = np.argmax(similar, 1)  # nearest similar existing landmark
    b = np.flatnonzero(has)
    a_slot = slot[b, first_j[b]]
    qa, qb = ex_q[b, first_j[b]], dk["quality"][b].astype(np.float64)
    keep_new[b] = False  # duplicates: worse (or equal) ones are dropped, better ones replace
    better = qb > qa
    bb, aa = b[better], a_slot[better]
    if not len(bb):
        return keep_new, none, none
    o = np.lexsort((-dk["quality"][bb], aa))  # per slot, best contender first
    bb, aa = bb[o], aa[o]
    firsts = np.r_[True, aa[1:] != aa[:-1]]
    return keep_new, aa[firsts], bb[firsts]


def _select_landmarks(maps, meta, dedup: bool, dedup_radius, min_cosine):
    """Which (source, row) pairs make the output, in output order (by source, then row: sequential
    voxel reads), and per-source counts. Later maps are deduplicated against what is there."""
    src = [np.zeros(len(maps[0]), np.int64)]
    row = [np.arange(len(maps[0]), dtype=np.int64)]
    stats = [dict(path=str(maps[0].path), landmarks=len(maps[0]), kept=len(maps[0]), dropped_duplicates=0, replaced=0)]
    for k in range(1, len(maps)):
        mk = maps[k]
        s_all, r_all = np.concatenate(src), np.concatenate(row)
        keep_new, replace_slot, replace_by = np.ones(len(mk), bool), np.zeros(0, np.int64), np.zeros(0, np.int64)
        if dedup and len(s_all) and len(mk):
            keep_new, replace_slot, replace_by = _duplicates(maps, meta, k, s_all, r_all, dedup_radius, min_cosine)
        # apply replacements, append new landmarks
        s_all = s_all.copy()
        r_all = r_all.copy()
        s_all[replace_slot] = k
        r_all[replace_slot] = replace_by
        new_rows = np.flatnonzero(keep_new)
        src, row = [s_all, np.full(len(new_rows), k, np.int64)], [r_all, new_rows]
        stats.append(
            dict(
                path=str(mk.path),
                landmarks=len(mk),
                kept=int(len(new_rows) + len(replace_slot)),
                dropped_duplicates=int(len(mk) - len(new_rows) - len(replace_slot)),
                replaced=int(len(replace_slot)),
            )
        )
    s_all, r_all = np.concatenate(src), np.concatenate(row)
    o = np.lexsort((r_all, s_all))
    s_all, r_all = s_all[o], r_all[o]
    for k, st in enumerate(stats):  # final counts (a replacing landmark may itself be replaced later)
        st["in_output"] = int(np.sum(s_all == k))
    return s_all, r_all, stats


def _landmark_arrays(meta, segs) -> tuple[dict, int]:
    """The output's landmark metadata by field name; colliding ids regenerated (and how many)."""
    lm = {key: np.concatenate([meta[k][key][rr] for k, rr in segs]) for key in meta[0]}
    ids = lm["ids"]
    _, first_idx = np.unique(ids, return_index=True)
    dup = np.ones(len(ids), bool)
    dup[first_idx] = False
    n_regen = int(dup.sum())
    if n_regen:
        ids = ids.copy()
        ids[dup] = new_landmark_ids(n_regen, avoid=ids[~dup])
    lm["ids"] = ids
    return lm, n_regen


def _camera_id(cameras: dict, cam) -> int:
    """The id of a camera equal to ``cam`` (model, size and parameters) in ``cameras``, or the next id,
    ``cam`` added under it."""
    for cid, c in cameras.items():
        if (c.model, c.width, c.height) == (cam.model, cam.width, cam.height) and np.array_equal(c.params, cam.params):
            return cid
    cameras[len(cameras)] = cam
    return len(cameras) - 1


def _frames(maps, sim: _Similarity | None):
    """Concatenated cameras (renumbered), frame names (collisions prefixed), frame cameras, poses
    (later maps moved by ``sim``) and the first frame row of each source."""
    cameras, names, frame_cam, cfw, frame_off = {}, [], [], [], []
    seen_names: set = set()
    for k, m in enumerate(maps):
        old_ids = sorted(m.cameras)
        new_ids = np.array([_camera_id(cameras, m.cameras[cid]) for cid in old_ids], np.int32)
        fc = np.asarray(m.frame_camera_ids, np.int64)
        frame_cam.append(new_ids[np.searchsorted(old_ids, fc)] if len(fc) else np.zeros(0, np.int32))
        T_k = np.asarray(m.cam_from_world, np.float64)
        if k > 0 and sim is not None:
            T_k = geometry.move_poses(T_k, sim.T)
        cfw.append(T_k)
        frame_off.append(sum(len(n) for n in names))
        nm = [n if n not in seen_names else f"{k}/{n}" for n in m.frame_names]
        seen_names.update(nm)
        names.append(nm)
    all_names = [n for nm in names for n in nm]
    frame_cam = np.concatenate(frame_cam) if frame_cam else np.zeros(0, np.int32)
    return cameras, all_names, frame_cam, np.concatenate(cfw).reshape(-1, 4, 4), frame_off


def _tracks(maps, s_all, r_all, frame_off, max_side: int, warnings: list):
    """Observations of the kept landmarks, rows remapped, pixels scaled to ``max_side``; their stored
    patches (tracks/patch) where every map holds them at one size and no pixel is rescaled, else None."""
    tl_out, tf_out, txy_out, patch_out = [], [], [], []
    scaled = [_frame_scale(m.cameras, np.asarray(m.frame_camera_ids), m.max_side, max_side) for m in maps]
    with_patches = [m.has_track_patches for m in maps]
    keep_patches = all(with_patches) and len({m.track_patch_radius for m in maps}) == 1
    keep_patches &= all(fs is None for fs in scaled)
    if any(with_patches) and not keep_patches:
        warnings.append(
            "the observation patches (tracks/patch) are dropped: not every map stores them at one size and resolution"
        )
    for k, m in enumerate(maps):
        remap = np.full(len(m), -1, np.int64)
        out_rows = np.flatnonzero(s_all == k)
        remap[r_all[out_rows]] = out_rows
        tl, tf, txy = m.tracks()
        keep = remap[tl] >= 0
        tl_out.append(remap[tl[keep]].astype(np.int32))
        tf_out.append((tf[keep].astype(np.int64) + frame_off[k]).astype(np.int32))
        xy = txy[keep].astype(np.float32)
        fs = scaled[k]
        if fs is not None:
            xy = (xy * fs[tf[keep]]).astype(np.float32)
        txy_out.append(xy)
        if keep_patches:
            patch_out.append(m.track_patches(np.flatnonzero(keep)))
    patches = np.concatenate(patch_out) if keep_patches else None
    return np.concatenate(tl_out), np.concatenate(tf_out), np.concatenate(txy_out).reshape(-1, 2), patches


def _merge(maps, out, dedup_radius, transform, min_cosine, dedup, chunk, progress) -> MergeResult:
    first = maps[0]
    warnings = []
    sim = _similarity(transform, first.grid_resolution, warnings)
    if len({m.render_samples for m in maps}) > 1:
        warnings.append(f"maps differ in render_samples; using the first map's ({first.render_samples})")
    meta = [_to_first_frame(m, sim if i > 0 else None) for i, m in enumerate(maps)]
    s_all, r_all, stats = _select_landmarks(maps, meta, dedup, dedup_radius, min_cosine)
    segs = [(k, r_all[s_all == k]) for k in range(len(maps))]
    lm, n_regen = _landmark_arrays(meta, segs)
    cameras, names, frame_cam, cfw, frame_off = _frames(maps, sim)
    tracks = _tracks(maps, s_all, r_all, frame_off, first.max_side, warnings)

    provenance = {
        "operation": "merge",
        "merge": {
            "sources": [
                dict(
                    path=str(m.path),
                    num_landmarks=len(m),
                    num_frames=m.num_frames,
                    created=m.created,
                    favormap_version=m.favormap_version,
                    provenance=m.provenance,
                )
                for m in maps
            ],
            "dedup": bool(dedup),
            "dedup_radius": dedup_radius if dedup_radius is not None else "voxel_size",
            "min_cosine": float(min_cosine),
            "transform_b_to_a": None if transform is None else np.asarray(transform).tolist(),
            "counts": stats,
            "ids_regenerated": n_regen,
            "warnings": warnings,
        },
    }
    header = {k: getattr(first, k) for k in MapWriter.HEADER_KEYS}
    header["provenance"] = provenance
    L, M = len(s_all), len(names)
    with MapWriter(out, header, L, M) as w:
        write_landmark_metadata(w, lm)
        write_frames_and_tracks(w, cameras, names, frame_cam, cfw, *tracks, cam_from_rig=first.stored_cam_from_rig)
        resample = {k: sim.W for k in range(1, len(maps))} if sim is not None and sim.W is not None else {}
        copy_voxels(w, [(maps[k], rr) for k, rr in segs], chunk=chunk, resample=resample, progress=progress)
    return MergeResult(out, L, M, len(cameras), stats, n_regen, warnings)


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
