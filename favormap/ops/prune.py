"""Pruning a map: filters (track length, quality, bounding box) and a landmark budget met with
spatially even coverage. Voxel grids are streamed into the output (never the whole map in memory).

Budget selection (:func:`spatially_even`): the scene is cut into cubic cells; the cell size is
found by bisection as the smallest one with at most N occupied cells; each occupied cell keeps its
best landmark (highest quality, then longest track), and the remaining budget goes to the
second-best of each cell, and so on, best first. So the kept landmarks cover every region of the
scene instead of the best region only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mapfile import Map
from ..mapfile.fields import field_name, metadata_datasets
from ..mapfile.writer import MapWriter, check_output_path
from .rewrite import copy_voxels, write_frames_and_tracks, write_landmark_metadata

REASONS = ("min_track", "min_quality", "bbox", "budget")


def reason_text(reason: str, res: PruneResult) -> str:
    """Why landmarks were removed, in words, with the setting that removed them."""
    p = res.params
    if reason == "min_track":
        return f"seen in fewer than {p['min_track']} frames (--min-track {p['min_track']})"
    if reason == "min_quality":
        return f"training PSNR below {p['min_quality']:g} dB (--min-quality {p['min_quality']:g})"
    if reason == "bbox":
        lo, hi = np.asarray(p["bbox"], float).reshape(2, 3)
        return f"outside the box ({', '.join(f'{v:g}' for v in lo)}) .. ({', '.join(f'{v:g}' for v in hi)}) (--bbox)"
    cell = f", one or more per grid cell of {res.cell_size:.4g} scene units" if res.cell_size else ""
    return f"over the budget of {p['max_landmarks']} landmarks, thinned evenly in space (--max-landmarks{cell})"


def removal_summary(res: PruneResult) -> str:
    """'1101 seen in fewer than 5 frames (--min-track 5), ...' for the reasons that removed landmarks."""
    return "; ".join(f"{v} {reason_text(k, res)}" for k, v in res.removed.items() if v) or "nothing selected"


def _cell_keys(p: np.ndarray, lo: np.ndarray, cell: float) -> np.ndarray:
    ijk = np.floor((p - lo) / cell).astype(np.int64)
    dims = ijk.max(0) + 1
    return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]


def occupied_cells(positions: np.ndarray, cell: float, lo: np.ndarray | None = None) -> int:
    """Number of occupied cubic cells of side ``cell`` (grid anchored at ``lo``, default the minimum)."""
    if len(positions) == 0:
        return 0
    lo = positions.min(0) if lo is None else lo
    return len(np.unique(_cell_keys(positions, lo, cell)))


def even_cell_size(positions: np.ndarray, n: int, iterations: int = 60) -> float:
    """Smallest cell size (bisection, on a log scale) with at most ``n`` occupied cells."""
    lo_p = positions.min(0)
    extent = float((positions.max(0) - lo_p).max())
    if extent <= 0:
        return 1.0
    lo, hi = extent * 1e-6, extent * 1.001  # hi: one cell holds everything
    if occupied_cells(positions, lo, lo_p) <= n:
        return lo
    for _ in range(iterations):
        mid = np.sqrt(lo * hi)
        c = occupied_cells(positions, mid, lo_p)
        if c <= n:
            hi = mid
            if c >= 0.995 * n:
                break
        else:
            lo = mid
        if hi / lo < 1 + 1e-4:
            break
    return hi


def spatially_even(
    positions: np.ndarray, score: np.ndarray, n: int, tiebreak: np.ndarray | None = None, cell: float | None = None
) -> np.ndarray:
    """Sorted rows of at most ``n`` landmarks spread evenly: per occupied cell the best ``score``
    first, ties broken by the larger ``tiebreak`` (see the module docstring). ``cell``: the cell
    size (default :func:`even_cell_size`)."""
    positions = np.asarray(positions, np.float64)
    L = len(positions)
    if n <= 0:
        return np.zeros(0, np.int64)
    if L <= n:
        return np.arange(L, dtype=np.int64)
    cell = even_cell_size(positions, n) if cell is None else cell
    key = _cell_keys(positions, positions.min(0), cell)
    tb = np.zeros(L) if tiebreak is None else -np.asarray(tiebreak, np.float64)
    order = np.lexsort((tb, -np.asarray(score, np.float64), key))  # by cell, best first
    k_sorted = key[order]
    starts = np.r_[0, np.flatnonzero(k_sorted[1:] != k_sorted[:-1]) + 1]
    rank = np.arange(L) - np.repeat(starts, np.diff(np.r_[starts, L]))
    rank_of = np.empty(L, np.int64)
    rank_of[order] = rank
    pick = np.lexsort((tb, -np.asarray(score, np.float64), rank_of))[:n]
    return np.sort(pick)


def parse_bbox(text) -> np.ndarray:
    """'x0,y0,z0,x1,y1,z1' -> (2, 3) [min, max]."""
    if isinstance(text, str):
        try:
            vals = [float(v) for v in text.replace(" ", ",").split(",") if v != ""]
        except ValueError:
            raise InputError(f"--bbox expects six numbers x0,y0,z0,x1,y1,z1, got {text!r}") from None
    else:
        vals = list(np.asarray(text, float).ravel())
    if len(vals) != 6 or not np.all(np.isfinite(vals)):
        raise InputError(f"--bbox expects six finite numbers x0,y0,z0,x1,y1,z1, got {text!r}")
    b = np.array(vals).reshape(2, 3)
    return np.stack([b.min(0), b.max(0)])


@dataclass
class PruneResult:
    path: Path | None
    num_before: int
    num_after: int
    removed: dict = field(default_factory=dict)  # reason -> count (each landmark counted once, first reason)
    failing: dict = field(default_factory=dict)  # reason -> landmarks failing it (may overlap)
    cell_size: float | None = None
    rows: np.ndarray | None = None
    params: dict = field(default_factory=dict)  # the settings: max_landmarks, min_track, min_quality, bbox

    def to_dict(self) -> dict:
        return {
            "output": None if self.path is None else str(self.path),
            "num_before": self.num_before,
            "num_after": self.num_after,
            "removed": self.removed,
            "failing": self.failing,
            "cell_size": self.cell_size,
        }


def select_rows(
    m, max_landmarks: int | None = None, min_track: int | None = None, min_quality: float | None = None, bbox=None
) -> PruneResult:
    """Which landmarks of ``m`` (a Map or MapData) to keep, and why the others go."""
    L = len(m.ids)
    keep = np.ones(L, bool)
    removed, failing = {}, {}
    tests = []
    if min_track is not None:
        tests.append(("min_track", np.asarray(m.track_length) >= min_track))
    if min_quality is not None:
        tests.append(("min_quality", np.asarray(m.quality, np.float64) >= min_quality))
    if bbox is not None:
        b = parse_bbox(bbox)
        p = np.asarray(m.positions)
        tests.append(("bbox", np.all((p >= b[0]) & (p <= b[1]), axis=1)))
    for name, ok in tests:
        failing[name] = int(np.sum(~ok))
        removed[name] = int(np.sum(keep & ~ok))
        keep &= ok
    rows = np.flatnonzero(keep)
    cell = None
    if max_landmarks is not None:
        if max_landmarks < 1:
            raise InputError(f"--max-landmarks must be >= 1, got {max_landmarks}")
        if len(rows) > max_landmarks:
            p = np.asarray(m.positions)[rows]
            cell = even_cell_size(p, max_landmarks)
            sel = spatially_even(p, np.asarray(m.quality)[rows], max_landmarks, np.asarray(m.track_length)[rows], cell)
            removed["budget"] = failing["budget"] = int(len(rows) - len(sel))
            rows = rows[sel]
        else:
            removed["budget"] = failing["budget"] = 0
    params = {
        "max_landmarks": max_landmarks,
        "min_track": min_track,
        "min_quality": min_quality,
        "bbox": None if bbox is None else parse_bbox(bbox).tolist(),
    }
    return PruneResult(None, L, len(rows), removed, failing, cell, rows, params)


def prune_map(
    path,
    out,
    max_landmarks: int | None = None,
    min_track: int | None = None,
    min_quality: float | None = None,
    bbox=None,
    chunk: int = 4096,
    progress=None,
    allow_empty: bool = False,
) -> PruneResult:
    """Write the pruned map of ``path`` to ``out`` (atomic; voxel grids streamed)."""
    check_output_path(out, [path])  # fail before any work
    with Map.open(path) as m:
        res = select_rows(m, max_landmarks, min_track, min_quality, bbox)
        rows = res.rows
        if len(rows) == 0 and not allow_empty:
            raise InputError(
                f"pruning {path} would remove all {res.num_before} landmarks ({removal_summary(res)}); nothing written"
            )
        remap = np.full(len(m), -1, np.int64)
        remap[rows] = np.arange(len(rows))
        tl, tf, txy = m.tracks()
        obs = remap[tl] >= 0
        prov = dict(m.provenance)
        prov["operation"] = "prune"
        prov["prune"] = {
            "source": str(m.path),
            "num_before": res.num_before,
            "num_after": res.num_after,
            "max_landmarks": max_landmarks,
            "min_track": min_track,
            "min_quality": min_quality,
            "bbox": None if bbox is None else parse_bbox(bbox).tolist(),
            "removed": res.removed,
            "cell_size": res.cell_size,
        }
        header = {k: getattr(m, k) for k in MapWriter.HEADER_KEYS}
        header["provenance"] = prov
        with MapWriter(out, header, len(rows), m.num_frames) as w:
            write_landmark_metadata(w, {field_name(p): getattr(m, field_name(p))[rows] for p in metadata_datasets()})
            write_frames_and_tracks(
                w,
                m.cameras,
                m.frame_names,
                m.frame_camera_ids,
                m.cam_from_world,
                remap[tl[obs]].astype(np.int32),
                tf[obs],
                txy[obs],
                m.track_patches(np.flatnonzero(obs)) if m.has_track_patches else None,
                cam_from_rig=m.stored_cam_from_rig,
            )
            copy_voxels(w, [(m, rows)], chunk=chunk, progress=progress)
    res.path = Path(out)
    return res
