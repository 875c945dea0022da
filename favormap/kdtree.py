"""The KD-tree backends of :class:`favormap.visibility.SpatialIndex`, all returning the same rows:

- "auto": a numpy scan (``_NumpyScan``) for up to ``BRUTE_FORCE_MAX`` points, a ``scipy.spatial.cKDTree``
  above, decided per tree;
- "numpy": always the brute-force scan (no tree to build, nothing to import);
- "scipy": always a cKDTree;
- "open3d": Open3D's KDTreeFlann / NearestNeighborSearch.

scipy.spatial and Open3D are imported by their backends when a tree asks for them."""

from __future__ import annotations

import numpy as np

# The "auto" backend scans with numpy up to this many points per tree and builds a scipy cKDTree above:
# importing scipy.spatial is a large share of a one-shot localization, and a scan of a small tree costs about
# what a cKDTree query does (timings: docs/measurements.md, "Visibility backends")
BRUTE_FORCE_MAX = 50_000
_SCAN_CHUNK_BYTES = 64 << 20  # memory bound of one chunk of a numpy scan


class _NumpyScan:
    """Brute-force backend in numpy: every query scans all points. No tree to build and nothing to
    import, so it wins for small point sets (see BRUTE_FORCE_MAX). Returns what cKDTree returns:
    squared distances are summed in cKDTree's order (dx² + dy²) + dz² and compared with r², so the
    radius rows are identical (inclusive); k-NN ties are broken by the lower row."""

    def __init__(self, points: np.ndarray):
        P = np.asarray(points, np.float64).reshape(-1, 3)
        self.n = len(P)
        self.xyz = [np.ascontiguousarray(P[:, j]) for j in range(3)]  # one contiguous column per axis

    def _sq_dist(self, q: np.ndarray, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """(m, hi - lo) squared distances from the (m, 3) points ``q`` to points ``lo:hi``."""
        x, y, z = (c[lo:hi] for c in self.xyz)
        d2 = np.subtract(q[:, 0:1], x)
        d2 *= d2
        t = np.subtract(q[:, 1:2], y)
        t *= t
        d2 += t
        np.subtract(q[:, 2:3], z, out=t)
        t *= t
        d2 += t
        return d2

    def radius(self, center, r: float) -> np.ndarray:
        q = np.asarray(center, np.float64).reshape(1, 3)
        r2 = float(r) * float(r)
        step = max(1, _SCAN_CHUNK_BYTES // 24)  # about 3 float64 temporaries per scanned point
        out = [np.flatnonzero(self._sq_dist(q, lo, lo + step)[0] <= r2) + lo for lo in range(0, self.n, step)]
        return out[0] if len(out) == 1 else np.concatenate([np.zeros(0, np.int64), *out])

    def knn(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, k) rows and distances, nearest first (ties: lower row first); ``k`` <= len."""
        Q = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        n, N = len(Q), self.n
        rows = np.empty((n, k), np.int64)
        dist = np.empty((n, k))
        step = max(1, _SCAN_CHUNK_BYTES // (32 * max(N, 1)))  # d2, a temporary, the partition, a mask
        for s in range(0, n, step):
            d2 = self._sq_dist(Q[s : s + step])
            if k < N:
                part = np.argpartition(d2, k - 1, axis=1)[:, :k]
            else:
                part = np.broadcast_to(np.arange(N), d2.shape).copy()
            pd = np.take_along_axis(d2, part, 1)
            order = np.lexsort((part, pd), axis=-1)  # by distance, then by row
            part, pd = np.take_along_axis(part, order, 1), np.take_along_axis(pd, order, 1)
            if k < N:  # ties at the k-th distance: keep the lowest rows among them (as a stable sort)
                tied = np.flatnonzero(np.count_nonzero(d2 <= pd[:, -1:], axis=1) > k)
                for i in tied:
                    part[i] = np.argsort(d2[i], kind="stable")[:k]
                    pd[i] = d2[i, part[i]]
            rows[s : s + step] = part
            dist[s : s + step] = np.sqrt(pd)
        return rows, dist


class _ScipyTree:
    """KD-tree backend on scipy.spatial.cKDTree."""

    def __init__(self, points: np.ndarray):
        from scipy.spatial import cKDTree

        self.tree = cKDTree(points)

    def radius(self, center, r: float) -> np.ndarray:
        return np.asarray(self.tree.query_ball_point(np.asarray(center, np.float64).reshape(3), float(r)), np.int64)

    def knn(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, k) rows and distances, nearest first."""
        d, i = self.tree.query(np.asarray(points, np.float64).reshape(-1, 3), k=k)
        return np.asarray(i, np.int64).reshape(-1, k), np.asarray(d, np.float64).reshape(-1, k)


class _Open3DTree:
    """KD-tree backend on Open3D (KDTreeFlann for radius queries, the core NearestNeighborSearch
    for batched k-NN)."""

    def __init__(self, points: np.ndarray):
        import open3d as o3d

        self.o3d, self.points = o3d, points
        self.flann = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
        self._nns = None

    def radius(self, center, r: float) -> np.ndarray:
        _, idx, _ = self.flann.search_radius_vector_3d(np.asarray(center, np.float64).reshape(3), float(r))
        return np.asarray(idx, np.int64)

    def knn(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        o3d = self.o3d
        if self._nns is None:
            self._nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(self.points))
            self._nns.knn_index()
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        idx, d2 = self._nns.knn_search(o3d.core.Tensor(points), k)
        return (
            idx.numpy().astype(np.int64).reshape(len(points), k),
            np.sqrt(np.maximum(d2.numpy().reshape(len(points), k), 0)),
        )


def _auto_tree(points: np.ndarray):
    """The "auto" backend: a numpy scan for up to BRUTE_FORCE_MAX points, a scipy cKDTree above."""
    return (_NumpyScan if len(points) <= BRUTE_FORCE_MAX else _ScipyTree)(points)


KD_BACKENDS = {"auto": _auto_tree, "numpy": _NumpyScan, "scipy": _ScipyTree, "open3d": _Open3DTree}


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation sorting points along a Z-order (Morton) curve: neighbours in space end up near
    each other in memory, so KD-tree query results gather from few cache lines."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    if len(P) == 0:
        return np.zeros(0, np.int64)
    lo, ext = P.min(0), np.ptp(P, axis=0).max()
    q = np.floor((P - lo) / max(ext, 1e-12) * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(P), np.uint64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")
