"""tracking: keypoints followed through a posed sequence.

Frames are matched with their next ``window`` neighbours (in the order the frames are listed, or along
a path through their poses where that order is none: :mod:`favormap.frame_order`) by mutual nearest
neighbours on the descriptors; the known poses reject wrong matches (symmetric epipolar distance in
pixels). Matches are joined into tracks by connected components; a track that holds two different
keypoints of one frame is ambiguous and dropped. Tracks shorter than ``min_track`` are discarded.
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceABC
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from .features import Features
from .frame_order import matching_order
from .geometry import inverse
from .io import Camera
from .threads import serial_pools, thread_count


@dataclass
class Tracks:
    """Observations sorted by track: track j owns rows ``offsets[j]:offsets[j+1]``."""

    frame_idx: np.ndarray  # (O,) int32
    keypoint_idx: np.ndarray  # (O,) int32
    xy: np.ndarray  # (O, 2) float64 pixels
    offsets: np.ndarray  # (T+1,) int64
    # of the tracking run that made these tracks (0 for tracks derived from others): mutual matches between
    # frame pairs, how many of them lay within the epipolar limit and how many within 3x the limit. Most
    # mutual matches of frames far apart are wrong and lie anywhere; of the right ones, nearly all lie within
    # the limit when the poses are as accurate as it assumes, so a small share within the limit of those
    # within 3x says the poses are less accurate than that (favormap build prints it)
    matches: int = 0
    epipolar_matches: int = 0
    epipolar_matches_3x: int = 0
    # the epipolar limit the matches were held to (px), and the median distance of the right matches from
    # their epipolar line that chose it when the limit was measured (epipolar_limit; nan when it was given)
    max_epipolar_px: float = float("nan")
    epipolar_median_px: float = float("nan")
    # the order the run walked the frames in (favormap.frame_order.matching_order; None for derived tracks)
    frame_order: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.offsets) - 1

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def track_of_obs(self) -> np.ndarray:
        return np.repeat(np.arange(len(self)), self.lengths)

    def select(self, keep_obs: np.ndarray, min_len: int = 1) -> Tracks:
        """Keep the observations where ``keep_obs`` is True, then the tracks with >= min_len."""
        tid = self.track_of_obs
        counts = np.bincount(tid[keep_obs], minlength=len(self))
        keep = keep_obs & (counts[tid] >= min_len)
        return Tracks.from_obs(self.frame_idx[keep], self.keypoint_idx[keep], self.xy[keep], tid[keep])

    def range(self, lo: int, hi: int) -> Tracks:
        """Tracks lo..hi-1 (views: their observations are contiguous)."""
        a, b = self.offsets[lo], self.offsets[hi]
        return Tracks(self.frame_idx[a:b], self.keypoint_idx[a:b], self.xy[a:b], self.offsets[lo : hi + 1] - a)

    @classmethod
    def concat(cls, parts: list[Tracks]) -> Tracks:
        """The tracks of ``parts``, one after the other."""
        ends = np.cumsum([0] + [p.offsets[-1] for p in parts[:-1]])
        return cls(
            np.concatenate([p.frame_idx for p in parts]),
            np.concatenate([p.keypoint_idx for p in parts]),
            np.concatenate([p.xy for p in parts]),
            np.concatenate([[0]] + [p.offsets[1:] + e for p, e in zip(parts, ends)]).astype(np.int64),
        )

    @classmethod
    def from_obs(cls, frame_idx, keypoint_idx, xy, track_id) -> Tracks:
        order = np.lexsort((frame_idx, track_id))
        track_id = track_id[order]
        _, new_id = np.unique(track_id, return_inverse=True)
        counts = np.bincount(new_id) if len(new_id) else np.zeros(0, int)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return cls(
            frame_idx[order].astype(np.int32),
            keypoint_idx[order].astype(np.int32),
            xy[order].astype(np.float64),
            offsets,
        )


def fundamental(cam_from_world_a, K_a, cam_from_world_b, K_b) -> np.ndarray:
    """F with x_b^T F x_a = 0 (pixels)."""
    b_from_a = cam_from_world_b @ inverse(cam_from_world_a)
    R, t = b_from_a[:3, :3], b_from_a[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    return np.linalg.inv(K_b).T @ E @ np.linalg.inv(K_a)


def epipolar_distance(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distance in pixels."""
    ha = np.concatenate([xa, np.ones((len(xa), 1))], 1)
    hb = np.concatenate([xb, np.ones((len(xb), 1))], 1)
    la = ha @ F.T  # lines in b
    lb = hb @ F  # lines in a
    num = np.abs(np.sum(hb * la, 1))
    return 0.5 * (
        num / np.maximum(np.linalg.norm(la[:, :2], axis=1), 1e-12)
        + num / np.maximum(np.linalg.norm(lb[:, :2], axis=1), 1e-12)
    )


def mutual_nn(
    da: np.ndarray, db: np.ndarray, min_sim: float, ratio: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours with similarity >= ``min_sim`` (and, with ``ratio`` < 1, Lowe's ratio
    both ways): (rows of da, rows of db, their similarity). ``da``, ``db``: (N, C) unit descriptors
    (NumPy arrays, or CPU tensors)."""
    return _mutual(np.asarray(da) @ np.asarray(db).T, min_sim, ratio)


def _mutual(s: np.ndarray, min_sim: float, ratio: float):
    """Mutual nearest neighbours of a similarity matrix. A row's best column is mutual when its
    similarity is the column's maximum (ties: the first such row), which needs the columns' maxima
    but not their argmax (NumPy's row argmax and column max take ~2 ms for 2,048 x 2,048; torch's
    column argmax took ~14 ms, more than the matrix product)."""
    ia = np.arange(s.shape[0])
    if s.size == 0:
        return ia[:0], ia[:0], np.zeros(0, s.dtype)
    ab = s.argmax(1)
    best = s[ia, ab]
    ok = (best >= s.max(0)[ab]) & (best >= min_sim)
    if ratio < 1.0 and s.shape[1] > 1 and s.shape[0] > 1:
        # unit descriptors: distance^2 = 2 - 2 sim; the two best of each row and of each column
        dist = lambda v: np.sqrt(np.maximum(2.0 - 2.0 * v, 0.0))  # noqa: E731
        ta = -np.partition(-s, 1, axis=1)[:, :2]
        tb = -np.partition(-s, 1, axis=0)[:2]
        ta.sort(axis=1), tb.sort(axis=0)
        ok &= (dist(ta[:, 1]) < ratio * dist(ta[:, 0])) & (dist(tb[1, ab]) < ratio * dist(tb[0, ab]))
    ia, ab = ia[ok], ab[ok]
    _, first = np.unique(ab, return_index=True)  # a column that several rows reach at its maximum: the first
    keep = np.sort(first)
    return ia[keep], ab[keep], best[ok][keep]


def epipolar_distance_matrix(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """(Na, Nb) float32 symmetric epipolar distances (px) of every keypoint pair: :func:`epipolar_distance`
    for all pairs at once."""
    ha = np.concatenate([np.asarray(xa, np.float64), np.ones((len(xa), 1))], 1)
    hb = np.concatenate([np.asarray(xb, np.float64), np.ones((len(xb), 1))], 1)
    la = ha @ F.T  # (Na, 3) lines in b
    lb = hb @ F  # (Nb, 3) lines in a
    num = np.abs(la @ hb.T)  # (Na, Nb)
    inv_a = 1.0 / np.maximum(np.linalg.norm(la[:, :2], axis=1), 1e-12)
    inv_b = 1.0 / np.maximum(np.linalg.norm(lb[:, :2], axis=1), 1e-12)
    return (0.5 * num * (inv_a[:, None] + inv_b[None, :])).astype(np.float32)


def connected_components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The component of each of ``n`` nodes joined by the edges (a[i], b[i]): labels 0, 1, ... in the
    order of each component's smallest node, as ``scipy.sparse.csgraph.connected_components`` numbers
    them (whose import, ~0.25 s, was a build's only use of scipy.sparse). Union-find in NumPy: every
    edge between two trees hooks the larger root under the smallest root it meets, then pointers jump
    to their roots; an edge within one tree is done for good. A root is always its tree's smallest
    node, so the loop ends in O(log n) rounds."""
    parent = np.arange(n)
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    while len(a):
        pa, pb = parent[a], parent[b]
        lo, hi = np.minimum(pa, pb), np.maximum(pa, pb)
        open_ = lo != hi
        if not open_.any():
            break
        lo, hi, a, b = lo[open_], hi[open_], a[open_], b[open_]
        order = np.lexsort((lo, hi))  # by root to hook, then smallest new root first
        hi, lo = hi[order], lo[order]
        first = np.r_[True, hi[1:] != hi[:-1]]
        parent[hi[first]] = lo[first]
        while True:  # pointer jumping: every node to its root
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up
    return np.unique(parent, return_inverse=True)[1].reshape(-1)


def _counts(features) -> np.ndarray:
    counts = getattr(features, "counts", None)  # a feature cache knows them without reading the frames
    return np.asarray(counts() if callable(counts) else [len(f) for f in features], np.int64)


# epipolar_limit: the measured limit is this many times the right matches' median distance, within
# [the extractor's floor, EPIPOLAR_CEILING x the floor]; wrong matches are counted in a band of distances
# that right matches do not reach, and with fewer right matches than EPIPOLAR_MIN_MATCHES the floor is kept
EPIPOLAR_FACTOR = 3.0
EPIPOLAR_CEILING = 8.0
EPIPOLAR_MIN_MATCHES = 200
_WRONG_BAND = (32.0, 64.0)


def epipolar_limit(dist: np.ndarray, floor: float) -> tuple[float, float]:
    """The epipolar limit (px) measured from the distances ``dist`` of the mutual matches from their
    epipolar lines, and the median distance of the right ones it rests on: (limit, median).

    The poses' accuracy sets the spread of the right matches' distances; the wrong matches' distances
    are spread nearly evenly over tens of pixels. Their density per pixel is counted in a far band
    (``_WRONG_BAND``) and taken off the cumulative count, which leaves the right matches' distribution;
    the limit is ``EPIPOLAR_FACTOR`` times its median, no less than ``floor`` (the extractor's keypoint
    precision) and no more than ``EPIPOLAR_CEILING * floor``."""
    d = np.sort(np.asarray(dist, np.float64))
    lo, hi = _WRONG_BAND
    density = (np.searchsorted(d, hi, "right") - np.searchsorted(d, lo, "right")) / (hi - lo)
    grid = np.arange(1, int(lo * 20) + 1) / 20.0  # 0.05 px steps up to the band
    right = np.searchsorted(d, grid, "right") - density * grid
    n_right = right[-1]
    if n_right < EPIPOLAR_MIN_MATCHES:
        return float(floor), float("nan")
    median = float(grid[np.argmax(right >= 0.5 * n_right)])
    return float(np.clip(EPIPOLAR_FACTOR * median, floor, EPIPOLAR_CEILING * floor)), median


def track_features(
    features: SequenceABC[Features],
    cam_from_world: np.ndarray,
    cameras: list[Camera],
    min_track: int = 5,
    window: int = 3,
    max_epipolar_px: float | None = 2.0,
    min_similarity: float = 0.7,
    workers: int | None = None,
    min_epipolar_px: float = 1.0,
) -> Tracks:
    """Tracks of keypoints through a sequence of frames with known poses and pinhole cameras.
    ``workers``: threads matching frame pairs (None: favormap.threads' count); the tracks are the
    same whatever the count.

    ``features`` is read frame by frame (at most ``window + 1`` frames at a time), so it may be a
    :class:`favormap.features.cache.CachedFrames` of a sequence that does not fit in memory; only the
    matched keypoints are kept.

    ``max_epipolar_px`` None: the limit is measured from the mutual matches (:func:`epipolar_limit`, no
    less than ``min_epipolar_px``), so poses less accurate than the keypoints get a looser check."""
    counts = _counts(features)
    base = np.concatenate([[0], np.cumsum(counts)])  # global keypoint id of each frame's first keypoint
    workers = thread_count() if workers is None else int(workers)
    order = matching_order(cam_from_world)
    pairs = _match_pairs(features, counts, cam_from_world, cameras, order, window, min_similarity, workers)
    check = _EpipolarCheck.of(pairs, max_epipolar_px, min_epipolar_px)
    edges = _MatchEdges.within(pairs, check.max_epipolar_px, base)
    del pairs
    if not edges.count:
        empty = (np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros(1, np.int64))
        return check.recorded_in(Tracks(*empty, frame_order=order))
    graph = _MatchGraph.of(edges, base)
    del edges
    tracks = check.recorded_in(_consistent_tracks(graph, len(features), min_track))
    tracks.frame_order = order
    return tracks


@dataclass
class _PairMatches:
    """The mutual matches of frames a < b: keypoint indices, their pixels and epipolar distances."""

    a: int
    b: int
    ia: np.ndarray  # (M,) keypoints of frame a
    ib: np.ndarray  # (M,) keypoints of frame b
    xa: np.ndarray  # (M, 2) float32 pixels in a
    xb: np.ndarray  # (M, 2) float32 pixels in b
    dist: np.ndarray  # (M,) float32 symmetric epipolar distance (px)


def _match_pairs(
    features: SequenceABC[Features],
    counts: np.ndarray,
    cam_from_world: np.ndarray,
    cameras: list[Camera],
    order: np.ndarray,
    window: int,
    min_similarity: float,
    workers: int,
) -> list[_PairMatches]:
    """Every frame matched with its next ``window`` frames (mutual nearest neighbours) in ``order``
    (:func:`favormap.frame_order.matching_order`), holding at most ``window + 1`` frames' keypoints and
    descriptors at a time."""
    order = [int(i) for i in order]
    held: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (keypoints, descriptors)

    def frame(i):
        if i not in held:
            f = features[i]
            held[i] = (np.asarray(f.keypoints, np.float32), np.ascontiguousarray(f.descriptors, np.float32))
        return held[i]

    def match(a, b):
        (ka, da), (kb, db) = held[a], held[b]
        F = fundamental(cam_from_world[a], cameras[a].K, cam_from_world[b], cameras[b].K)
        ia, ib, _ = mutual_nn(da, db, min_similarity)
        return ia, ib, epipolar_distance(F, ka[ia], kb[ib]).astype(np.float32)

    found = []
    # the pairs of one frame on a pool of threads, one BLAS thread each (favormap.threads.serial_pools):
    # each similarity is one 128-term dot product whatever the thread count, and the NumPy reductions
    # after each product, which run on one core, overlap another pair's product. NumPy's OpenBLAS rather
    # than torch's MKL: faster for these shapes on one core (docs/implementation-notes.md, tracking)
    pool = ThreadPoolExecutor(workers, thread_name_prefix="favormap-track") if workers > 1 else None
    try:
        with serial_pools() if pool else nullcontext():
            for p, a in enumerate(order):
                if p:
                    held.pop(order[p - 1], None)
                bs = [b for b in order[p + 1 : p + 1 + window] if counts[a] and counts[b]]
                for i in [a, *bs]:
                    frame(i)
                lo, hi = [min(a, b) for b in bs], [max(a, b) for b in bs]
                results = pool.map(match, lo, hi) if pool else map(match, lo, hi)
                for x, y, (ix, iy, dist) in zip(lo, hi, results):
                    if len(ix):
                        found.append(_PairMatches(x, y, ix, iy, held[x][0][ix], held[y][0][iy], dist))
    finally:
        if pool:
            pool.shutdown()
    return found


@dataclass(frozen=True)
class _EpipolarCheck:
    """The epipolar limit the matches are held to (given, or measured: :func:`epipolar_limit`) and how
    many of the mutual matches lie within it and within 3x it, as :class:`Tracks` records them."""

    max_epipolar_px: float
    epipolar_median_px: float  # nan when the limit was given
    matches: int
    epipolar_matches: int
    epipolar_matches_3x: int

    @classmethod
    def of(cls, pairs: list[_PairMatches], max_epipolar_px: float | None, min_epipolar_px: float) -> _EpipolarCheck:
        dist = np.concatenate([p.dist for p in pairs]) if pairs else np.zeros(0, np.float32)
        median = float("nan")
        if max_epipolar_px is None:
            max_epipolar_px, median = epipolar_limit(dist, min_epipolar_px)
        return cls(
            max_epipolar_px=float(max_epipolar_px),
            epipolar_median_px=median,
            matches=len(dist),
            epipolar_matches=int((dist <= max_epipolar_px).sum()),
            epipolar_matches_3x=int((dist <= 3 * max_epipolar_px).sum()),
        )

    def recorded_in(self, tracks: Tracks) -> Tracks:
        for k in ("matches", "epipolar_matches", "epipolar_matches_3x", "max_epipolar_px", "epipolar_median_px"):
            setattr(tracks, k, getattr(self, k))
        return tracks


@dataclass
class _MatchEdges:
    """The matches within the epipolar limit as edges between global keypoint ids, with their pixels."""

    rows: list[np.ndarray]  # per frame pair, the global ids of the matched keypoints in the earlier frame
    cols: list[np.ndarray]  # ... in the later frame
    xy_rows: list[np.ndarray]
    xy_cols: list[np.ndarray]

    @property
    def count(self) -> int:
        return sum(len(r) for r in self.rows)

    @classmethod
    def within(cls, pairs: list[_PairMatches], max_epipolar_px: float, base: np.ndarray) -> _MatchEdges:
        gid = np.int32 if base[-1] < np.iinfo(np.int32).max else np.int64  # global keypoint ids of the edges
        edges = cls([], [], [], [])
        for p in pairs:
            ok = p.dist <= max_epipolar_px
            edges.rows.append((base[p.a] + p.ia[ok]).astype(gid))
            edges.cols.append((base[p.b] + p.ib[ok]).astype(gid))
            edges.xy_rows.append(p.xa[ok])
            edges.xy_cols.append(p.xb[ok])
        return edges


@dataclass
class _MatchGraph:
    """The graph of the matched keypoints only: its nodes (keypoints) and the matches between them."""

    node_frame: np.ndarray  # (m,) frame of each node
    node_kp: np.ndarray  # (m,) its keypoint in the frame
    node_xy: np.ndarray  # (m, 2) its pixel
    r: np.ndarray  # (E,) edges' first nodes
    c: np.ndarray  # (E,) and second

    @classmethod
    def of(cls, edges: _MatchEdges, base: np.ndarray) -> _MatchGraph:
        ends = np.concatenate(edges.rows + edges.cols)
        node_id, first, inv = np.unique(ends, return_index=True, return_inverse=True)
        node_xy = np.concatenate(edges.xy_rows + edges.xy_cols)[first]
        node_frame = (np.searchsorted(base, node_id, side="right") - 1).astype(np.int64)
        node_kp = node_id.astype(np.int64) - base[node_frame]
        return cls(node_frame, node_kp, node_xy, inv[: len(inv) // 2], inv[len(inv) // 2 :])


def _consistent_tracks(graph: _MatchGraph, n_frames: int, min_track: int) -> Tracks:
    """The graph's connected components as tracks, less those that hold two keypoints of one frame
    (ambiguous) and those of fewer than ``min_track`` frames."""
    n = n_frames
    label = connected_components(len(graph.node_frame), graph.r, graph.c)
    pairs = label.astype(np.int64) * n + graph.node_frame
    uniq_pairs, pair_counts = np.unique(pairs, return_counts=True)
    bad_labels = np.unique(uniq_pairs[pair_counts > 1] // n)
    frames_per_track = np.bincount(uniq_pairs // n, minlength=label.max() + 1)
    ok = ~np.isin(label, bad_labels) & (frames_per_track[label] >= min_track)
    return Tracks.from_obs(graph.node_frame[ok], graph.node_kp[ok], graph.node_xy[ok].astype(np.float64), label[ok])
