"""Matching a query's descriptors to landmark descriptors: mutual nearest neighbours over the whole
set (:func:`match_descriptors`, optionally with Lowe's ratio) or only within a radius of each landmark's projection
(:func:`match_near`, the guided step, optionally gated by a Mahalanobis distance). NumPy and OpenCV's
gemm; no torch, no Open3D."""

from __future__ import annotations

import cv2
import numpy as np

from .refine import mahalanobis2


def match_descriptors(
    rendered: np.ndarray,
    query: np.ndarray,
    threshold: float,
    mutual: bool = False,
    ratio: float = 1.0,
    chunk: int = 1024,
) -> np.ndarray:
    """(K, 2) index pairs [rendered row, query row]: for every rendered descriptor the most similar
    query descriptor, kept when the cosine similarity reaches ``threshold``, when (``mutual``) the
    rendered descriptor is also that query descriptor's most similar one, and when the best
    distance is below ``ratio`` times the second best (Lowe's test on unit vectors).

    NumPy, ``chunk`` rendered rows at a time, every block of similarities written into one buffer
    (``chunk`` x Q float32, a few MB): memory stays bounded when matching a query against a whole map
    (the prior-free step), and the products land in memory already mapped, where a fresh array per
    product (40 MB for 6,600 landmarks against 1,500 keypoints) is a fresh mapping of memory, page
    faults included, on every call (the products took ~1.8x as long); ties go to the lower index."""
    rendered = np.asarray(rendered, np.float32)
    nearest = NearestDescriptors(query, len(rendered), chunk, second=ratio < 1.0)
    for s in range(0, len(rendered), chunk):
        nearest.add(np.arange(s, min(s + chunk, len(rendered))), rendered[s : s + chunk])
    return nearest.matches(threshold, mutual, ratio)


class NearestDescriptors:
    """The pairs of :func:`match_descriptors`, accumulated from blocks of the ``n`` rendered descriptors in
    any order (e.g. while the next blocks are rendered): :meth:`add` compares a block with every query
    descriptor, :meth:`matches` gives the pairs once every row was added. The result does not depend on
    the blocks' order or sizes. ``second``: keep each row's second best (Lowe's ratio). Threads that
    share the rows each add theirs to one of :meth:`parts`."""

    def __init__(self, query: np.ndarray, n: int, chunk: int = 1024, second: bool = False):
        self.query = np.ascontiguousarray(np.asarray(query, np.float32))
        self.n, self.chunk = n, chunk
        G = len(self.query)
        self.best = np.zeros(n, np.int64)  # best column
        self.best_sim = np.full(n, -np.inf, np.float32)
        self.second = np.full(n, -np.inf, np.float32) if second else None
        self.col_best = np.full(G, -np.inf, np.float32)  # each query descriptor's best similarity
        self._buf = np.empty((min(chunk, n), G), np.float32) if n and G else None

    def parts(self, k: int) -> list[NearestDescriptors]:
        """``k`` accumulators for threads that add disjoint rows at the same time: each compares into a buffer
        of its own and writes its rows' bests into this one's arrays; :meth:`join` takes their query-side bests
        once they are done."""
        out = []
        for _ in range(k):
            p = object.__new__(NearestDescriptors)
            p.query, p.n, p.chunk = self.query, self.n, self.chunk
            p.best, p.best_sim, p.second = self.best, self.best_sim, self.second
            p.col_best = np.full(len(self.query), -np.inf, np.float32)
            p._buf = None if self._buf is None else np.empty_like(self._buf)
            out.append(p)
        return out

    def join(self, parts: list[NearestDescriptors]) -> None:
        for p in parts:
            np.maximum(self.col_best, p.col_best, out=self.col_best)

    def add(self, rows: np.ndarray, block: np.ndarray) -> None:
        """Rendered descriptors ``block`` (len(rows), C) of rows ``rows`` (indices into the n)."""
        if self._buf is None or len(rows) == 0:
            return
        block = np.asarray(block, np.float32)
        for s in range(0, len(rows), self.chunk):
            r, sim = (
                rows[s : s + self.chunk],
                _gemm_t(np.ascontiguousarray(block[s : s + self.chunk]), self.query, self._buf),
            )
            i = np.arange(len(sim))
            np.maximum(self.col_best, sim.max(0), out=self.col_best)  # max along axis 0: ~20x faster than argmax
            b = sim.argmax(1)
            self.best[r], self.best_sim[r] = b, sim[i, b]
            if self.second is not None and sim.shape[1] >= 2:
                sim[i, b] = -np.inf
                self.second[r] = sim.max(1)

    def matches(self, threshold: float, mutual: bool = False, ratio: float = 1.0) -> np.ndarray:
        if self._buf is None:
            return np.zeros((0, 2), np.int64)
        ok = self.best_sim >= threshold
        if ratio < 1.0 and len(self.query) >= 2:
            if self.second is None:
                raise ValueError("a ratio test needs the second best (NearestDescriptors(second=True))")
            ok &= np.maximum(2 - 2 * self.best_sim, 0) < ratio**2 * np.maximum(2 - 2 * self.second, 0)
        if mutual:  # the rendered row is its query descriptor's best; on a tie the lowest row wins
            ok &= self.best_sim >= self.col_best[self.best]
        idx = np.flatnonzero(ok)
        if mutual:
            _, first = np.unique(self.best[idx], return_index=True)
            idx = idx[np.sort(first)]
        return np.stack([idx, self.best[idx]], 1).astype(np.int64)


def _gemm_t(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """a @ b.T for float32 matrices through OpenCV's gemm (b is read transposed, not copied), written into the
    first len(a) rows of ``out`` (C-contiguous, len(b) columns). OpenCV's gemm runs on the OpenBLAS its wheel
    bundles, whose idle threads spin after each product as NumPy's do (favormap.threads.serial_blas)."""
    dst = out[: len(a)]
    if a.size == 0 or b.size == 0:
        dst[:] = 0
        return dst
    got = cv2.gemm(a, b, 1.0, None, 0.0, dst, flags=cv2.GEMM_2_T)
    return dst if got is dst or np.shares_memory(got, dst) else got


def pair_in(pairs: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(K,) bool: which rows of ``pairs`` (K, 2) also occur in ``known`` (M, 2)."""
    if len(pairs) == 0 or len(known) == 0:
        return np.zeros(len(pairs), bool)
    base = int(max(pairs[:, 1].max(), known[:, 1].max())) + 1
    return np.isin(pairs[:, 0] * base + pairs[:, 1], known[:, 0] * base + known[:, 1])


def distinct_pairs(m: np.ndarray, desc_rows: np.ndarray, n_landmarks: int) -> np.ndarray:
    """Matches (K, 2) [descriptor, query keypoint] without repeated (landmark, keypoint) pairs, which
    arise when each of the ``n_landmarks`` has several descriptors (``desc_rows``: the landmark of
    each descriptor; the first of a repeated pair is kept)."""
    if len(m) < 2 or len(desc_rows) == n_landmarks:
        return m
    _, keep = np.unique(np.c_[desc_rows[m[:, 0]], m[:, 1]], axis=0, return_index=True)
    return m[np.sort(keep)]


def radius_pairs(points: np.ndarray, keypoints: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j) with ``|points[i] - keypoints[j]| <= radius`` (pixels; rows of ``points``
    that are not finite pair with nothing). NumPy: the keypoints are binned into square cells of
    side ``radius`` (larger where that would make more than ~1,000 cells a side), a table gives each
    cell's run of keypoints, and each point looks at the 3 x 3 cells around its own."""
    points = np.asarray(points, np.float64).reshape(-1, 2)
    keypoints = np.asarray(keypoints, np.float64).reshape(-1, 2)
    ok = np.flatnonzero(np.all(np.isfinite(points), axis=1))
    empty = np.zeros(0, np.int64)
    if len(ok) == 0 or len(keypoints) == 0 or not radius > 0:
        return empty, empty
    lo = keypoints.min(0)
    cell = max(float(radius), float(np.ptp(keypoints, axis=0).max()) / 1024)
    ck = np.floor((keypoints - lo) / cell).astype(np.int64)
    cp = np.floor((points[ok] - lo) / cell).astype(np.int64)
    hi = ck.max(0)
    inside = np.all((cp >= -1) & (cp <= hi + 1), axis=1)  # points near the keypoints' extent
    ok, cp = ok[inside], cp[inside]
    width = int(hi[1]) + 5  # two empty cells each side: a point's 3 x 3 cells lie within the table
    ncell = (int(hi[0]) + 5) * width
    key = (ck[:, 0] + 2) * width + (ck[:, 1] + 2)
    order = np.argsort(key, kind="stable")
    count = np.bincount(key, minlength=ncell)
    start = np.cumsum(count) - count  # each cell's first keypoint in ``order``
    base = (cp[:, 0] + 2) * width + (cp[:, 1] + 2)
    ii, jj = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            q = base + (dx * width + dy)
            n = count[q]
            total = int(n.sum())
            if not total:
                continue
            rows = np.repeat(np.arange(len(q)), n)
            ii.append(ok[rows])
            jj.append(order[np.repeat(start[q] - np.cumsum(n) + n, n) + np.arange(total)])
    if not ii:
        return empty, empty
    i, j = np.concatenate(ii), np.concatenate(jj)
    near = np.sum((points[i] - keypoints[j]) ** 2, axis=1) <= radius**2
    return i[near], j[near]


def match_near(
    rendered: np.ndarray,
    query: np.ndarray,
    uv: np.ndarray,
    keypoints: np.ndarray,
    radius: float,
    threshold: float,
    mutual: bool = True,
    gate: tuple[np.ndarray, float] | None = None,
) -> np.ndarray:
    """:func:`match_descriptors` restricted to pairs whose query keypoint (``keypoints`` (Q, 2))
    lies within ``radius`` pixels of the landmark's projection ``uv`` (L, 2) (:func:`radius_pairs`):
    the best query keypoint near each landmark, kept when its cosine reaches
    ``threshold`` and (``mutual``) the landmark is also the best among those near that keypoint.
    With ``gate`` = (information (L, 2, 2), d2_max), a pair must also have a squared Mahalanobis
    distance r^T info r <= d2_max from the projection. Only the candidate pairs are compared, not
    the full similarity matrix."""
    rendered = np.asarray(rendered, np.float32)
    query = np.asarray(query, np.float32)
    keypoints = np.asarray(keypoints, np.float64).reshape(-1, 2)
    li, kj = radius_pairs(uv, keypoints, radius)
    if len(rendered) == 0 or len(li) == 0:
        return np.zeros((0, 2), np.int64)
    if gate is not None:
        info, d2_max = gate
        r = keypoints[kj] - uv[li]
        inside = mahalanobis2(info[li], r) <= d2_max
        li, kj = li[inside], kj[inside]
    sim = np.einsum("ij,ij->i", rendered[li], query[kj])
    best_l = np.full(len(rendered), -3.0, np.float32)
    np.maximum.at(best_l, li, sim)
    keep = (sim == best_l[li]) & (sim >= threshold)
    if mutual:  # the landmark is also the keypoint's best among all landmarks near it
        best_k = np.full(len(query), -3.0, np.float32)
        np.maximum.at(best_k, kj, sim)
        keep &= sim == best_k[kj]
    out = np.stack([li[keep], kj[keep]], 1)
    # ties (equal similarity): one pair per landmark and per keypoint
    _, first = np.unique(out[:, 0], return_index=True)
    out = out[np.sort(first)]
    _, first = np.unique(out[:, 1], return_index=True)
    out = out[np.sort(first)]
    return out[np.argsort(out[:, 0], kind="stable")]  # by landmark, as match_descriptors (RANSAC sees the same order)


def pair_similarity(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Cosine of the matched pairs ``m`` (K, 2) of unit rows ``a`` and ``b``."""
    return np.einsum("ij,ij->i", a[m[:, 0]], b[m[:, 1]]) if len(m) else np.zeros(0, np.float32)
