"""Which landmarks a camera can see: a spatial index over landmark positions with radius, k-NN,
frustum and visibility queries, and the exact per-landmark visibility test (in front, inside the
image, within the distance and viewing-angle range the landmark was trained for; paper sec. 3.3).

Used by the localizer, the evaluation diagnostics and the map operations (query, merge, prune).
The index's KD-tree backends (a numpy scan for small maps, scipy's cKDTree, Open3D's) are in
:mod:`favormap.kdtree`; all return the same rows.

Frustum and visibility queries are exact: the index only gathers candidates inside a sphere that
encloses the frustum, and the candidates then go through the same projection / depth / viewing-angle
tests a brute-force scan would apply (``visible_mask``), so the result equals the brute-force one.
Trees are built on first use (``prepare_visibility`` builds the visibility ones up front).
This module needs numpy only; scipy.spatial and Open3D are imported by their backends when a tree
asks for them, so the localization path runs where Open3D is not installed.
"""

from __future__ import annotations

import numpy as np

from .geometry import camera_centers, project, unproject
from .io import Camera
from .kdtree import KD_BACKENDS, morton_order  # noqa: F401  (morton_order: re-exported)
from .view_limits import ViewLimits

# Visibility queries group landmarks into tiers by reach (max training distance x depth_scale):
# each tier is searched with the bounding sphere of a frustum as deep as the tier's largest reach,
# so landmarks only visible from nearby are not gathered from far away. Landmarks above the top
# quantile are tested directly, so that a few landmarks seen from far away do not blow up the
# sphere for every query.
_TIER_QUANTILES = (0.25, 0.5, 0.75, 0.99)
# up to this many landmarks every query tests all of them directly: one vectorised test (~1 ms for 12,000) costs
# less than gathering candidates from the tiers where a query may see most of the map (a room: 2.6 ms)
_DIRECT_MAX = 20_000


class SpatialIndex:
    """Spatial index over (L, 3) positions (its tree built on first use) with radius, k-NN,
    frustum and visibility queries.

    ``backend``: "auto" (the default, used on the localization path: a numpy scan for up to
    ``BRUTE_FORCE_MAX`` points, ``scipy.spatial.cKDTree`` above; decided per tree, so each
    visibility tier picks on its own size), "numpy" (always the scan), "scipy" (always a cKDTree)
    or "open3d" (Open3D's KDTreeFlann / NearestNeighborSearch; the map operations use it). All
    return the same rows (tests/test_spatial.py)."""

    def __init__(self, positions: np.ndarray, backend: str = "auto"):
        if backend not in KD_BACKENDS:
            raise ValueError(f"unknown KD-tree backend {backend!r} (choose from {', '.join(KD_BACKENDS)})")
        self.positions = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
        self.backend = backend
        self._kdtree = None
        self._tiers = None

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def _tree(self):
        if self._kdtree is None and len(self.positions):
            self._kdtree = KD_BACKENDS[self.backend](self.positions)
        return self._kdtree

    # -- single queries -----------------------------------------------------------------------
    def radius(self, center, r: float) -> np.ndarray:
        """Rows within distance ``r`` of ``center`` (sorted)."""
        if len(self) == 0 or not r >= 0:
            return np.zeros(0, np.int64)
        if not np.isfinite(r):
            return np.arange(len(self), dtype=np.int64)
        return np.sort(self._tree.radius(center, r))

    def knn(self, center, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows and distances of the ``k`` nearest landmarks (nearest first)."""
        if len(self) == 0 or k <= 0:
            return np.zeros(0, np.int64), np.zeros(0)
        rows, dist = self._tree.knn(np.asarray(center, np.float64).reshape(1, 3), int(min(k, len(self))))
        return rows[0], dist[0]

    # -- batched queries ----------------------------------------------------------------------
    def knn_batch(self, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, k) rows and distances of the ``k`` nearest landmarks of each query point, nearest
        first; rows are -1 and distances inf where the index has fewer than ``k`` points."""
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        rows = np.full((len(points), max(k, 0)), -1, np.int64)
        dist = np.full((len(points), max(k, 0)), np.inf)
        kk = min(k, len(self))
        if kk <= 0 or len(points) == 0:
            return rows, dist
        rows[:, :kk], dist[:, :kk] = self._tree.knn(points, kk)
        return rows, dist

    # -- frustum ------------------------------------------------------------------------------
    def frustum(
        self, camera: Camera, cam_from_world: np.ndarray, max_depth: float, min_depth: float = 0.0
    ) -> np.ndarray:
        """Rows (sorted) of landmarks inside the pinhole camera's frustum between ``min_depth`` and
        ``max_depth`` (z in the camera frame): a KD-tree radius query around a sphere enclosing the
        frustum, then an exact projection test on the candidates."""
        if len(self) == 0:
            return np.zeros(0, np.int64)
        if not np.isfinite(max_depth):
            cand = np.arange(len(self), dtype=np.int64)
        else:
            center, r = frustum_sphere(camera, cam_from_world, max_depth, min_depth)
            cand = self.radius(center, r * (1 + 1e-9) + 1e-12)
        return cand[project_inside(self.positions[cand], camera, cam_from_world, min_depth, max_depth)]

    # -- visibility tiers ------------------------------------------------------------------------
    def prepare_visibility(
        self,
        depth_range: np.ndarray,
        depth_scale: float = ViewLimits.depth_scale[1],
        view_dir: np.ndarray | None = None,
        view_angle: np.ndarray | None = None,
    ):
        """Build (or reuse) the reach tiers used by :func:`visible_rows` for these arrays (the same
        objects) and scale. Called by visible_rows on first use; call it to pay the cost up front."""
        t = self._tiers
        if t is not None and t.matches(depth_range, depth_scale, view_dir, view_angle):
            return t
        self._tiers = _Tiers(self, depth_range, depth_scale, view_dir, view_angle)
        return self._tiers


class _Tiers:
    """Landmarks grouped by reach, one KD-tree per group (see _TIER_QUANTILES). Each group keeps
    its rows in Morton order with local copies of their positions, reaches and (when given) view
    directions, view angles and depth ranges, so that a query gathers from few cache lines."""

    def __init__(self, index: SpatialIndex, depth_range: np.ndarray, scale: float, view_dir=None, view_angle=None):
        # the source arrays are kept: their identity is the cache key (and stays valid)
        self.src = (depth_range, view_dir, view_angle)
        self.scale, self.shape = scale, depth_range.shape
        reach = np.asarray(depth_range[:, 1], np.float64) * scale
        L = len(reach)
        self.tiers = []  # dicts: depth, rows (global), P, reach, tree or None, [vd, va, dr]
        self.num_direct = 0
        if L == 0:
            return
        if L <= _DIRECT_MAX:
            bounds = []
        else:
            bounds = [float(np.quantile(reach, q)) for q in _TIER_QUANTILES]
            bounds = sorted(set(bounds + [min(float(reach.max()), 2 * bounds[-1])]))
        lo = -np.inf
        for b in bounds + [np.inf]:  # the last group (beyond twice the 99 % reach) is tested directly
            rows = np.flatnonzero((reach > lo) & (reach <= b))
            lo = b
            if not len(rows):
                continue
            if bounds:
                rows = rows[morton_order(index.positions[rows])]
            P = np.ascontiguousarray(index.positions[rows])
            t = dict(depth=b, rows=rows, P=P, reach=reach[rows])
            t["tree"] = KD_BACKENDS[index.backend](t["P"]) if np.isfinite(b) else None
            if view_dir is not None and view_angle is not None:
                t.update(
                    vd=np.ascontiguousarray(view_dir[rows]),
                    va=view_angle[rows],
                    dr=np.ascontiguousarray(depth_range[rows]),
                )
            if t["tree"] is None:
                self.num_direct = len(rows)
            self.tiers.append(t)

    def matches(self, depth_range, scale, view_dir, view_angle) -> bool:
        d, v, a = self.src
        local = view_dir is None or (v is view_dir and a is view_angle)
        return d is depth_range and self.scale == scale and self.shape == depth_range.shape and local

    def _near(self, t: dict, camera: Camera, cam_from_world: np.ndarray, c: np.ndarray, unit: tuple):
        """Local indices of tier ``t`` inside the sphere around the view pyramid within the tier's
        reach of the camera, then within their own reach of the camera (a loose bound: the exact
        test is visible_mask's). Returns (indices, their positions)."""
        if t["tree"] is None:
            idx = np.arange(len(t["rows"]))
        else:
            depth = t["depth"]
            idx = t["tree"].radius(c + depth * (unit[0] - c), depth * unit[1] * (1 + 1e-9) + 1e-9 * depth)
            idx.sort()
        p = t["P"][idx]
        d = p - c
        keep = np.einsum("ij,ij->i", d, d) <= np.square(t["reach"][idx] * (1 + 1e-6) + 1e-9)
        return idx[keep], p[keep]

    def candidates(self, camera: Camera, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sorted rows (and their positions) that may be visible."""
        c = camera_centers(cam_from_world)
        unit = reach_sphere(camera, cam_from_world, 1.0)  # the sphere scales with the reach
        rows, pos = [np.zeros(0, np.int64)], [np.zeros((0, 3))]
        for t in self.tiers:
            idx, p = self._near(t, camera, cam_from_world, c, unit)
            rows.append(t["rows"][idx])
            pos.append(p)
        rows = np.concatenate(rows)
        order = np.argsort(rows)
        return rows[order], np.concatenate(pos)[order]

    def visible(self, camera: Camera, cam_from_world: np.ndarray, limits: ViewLimits) -> np.ndarray:
        """Sorted visible rows (needs the local view arrays)."""
        c = camera_centers(cam_from_world)
        unit = reach_sphere(camera, cam_from_world, 1.0)
        out = [np.zeros(0, np.int64)]
        for t in self.tiers:
            if t["tree"] is None:  # a group without a tree (a small map's only one): every landmark tested, exactly
                out.append(t["rows"][visible_mask(t["P"], camera, cam_from_world, t["vd"], t["va"], t["dr"], limits)])
                continue
            idx, p = self._near(t, camera, cam_from_world, c, unit)
            ok = visible_mask(p, camera, cam_from_world, t["vd"][idx], t["va"][idx], t["dr"][idx], limits)
            out.append(t["rows"][idx[ok]])
        out = np.concatenate(out)
        out.sort()
        return out


def _min_radius(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre on the segment a-b minimising the distance to the farthest of ``pts`` (a convex
    function along the segment): coarse grid, then a finer one around the best sample."""
    lo, hi = 0.0, 1.0
    for _ in range(3):
        s = np.linspace(lo, hi, 17)
        centers = a + s[:, None] * (b - a)
        radii = np.linalg.norm(pts[None] - centers[:, None], axis=2).max(1)
        i = int(np.argmin(radii))
        step = (hi - lo) / 16
        lo, hi = max(0.0, s[i] - step), min(1.0, s[i] + step)
    return centers[i], float(radii[i])


def _corners(camera: Camera) -> np.ndarray:
    return np.array([[0, 0], [camera.width, 0], [0, camera.height], [camera.width, camera.height]], float)


def frustum_sphere(
    camera: Camera, cam_from_world: np.ndarray, max_depth: float, min_depth: float = 0.0
) -> tuple[np.ndarray, float]:
    """A small sphere (centre, radius) enclosing the frustum between ``min_depth`` and ``max_depth``.

    The frustum is the convex hull of its near and far corners (the near ones collapse to the
    camera centre when ``min_depth`` is 0), so any sphere holding the corners holds it. The centre
    is searched on the segment between the near and far corner centroids, where the radius (the
    farthest corner) is a convex function of the position."""
    rays = unproject(camera.K, _corners(camera))
    wfc_R = cam_from_world[:3, :3].T
    c = camera_centers(cam_from_world)
    far = (rays * max_depth) @ wfc_R.T + c
    near = (rays * max(min_depth, 0.0)) @ wfc_R.T + c
    pts = np.vstack([far, near])
    return _min_radius(pts, near.mean(0), far.mean(0))


def reach_sphere(camera: Camera, cam_from_world: np.ndarray, reach: float) -> tuple[np.ndarray, float]:
    """A small sphere (centre, radius) enclosing the points of the view pyramid within distance
    ``reach`` of the camera centre (pyramid ∩ ball): smaller than the frustum cut at depth
    ``reach``.

    For a centre ``s u`` on a ray ``u`` inside the pyramid, the farthest point of pyramid ∩ ball is
    the apex or a corner ray's point at distance ``reach`` (|p - s u|² = ρ² + s² - 2 s ρ cos φ is
    convex in ρ, and the angle φ from ``u`` is largest at a vertex of the pyramid's cross-section),
    so the radius is exact over those 5 points. Falls back to :func:`frustum_sphere` for fields of
    view of 180 degrees or more."""
    rays = unproject(camera.K, _corners(camera))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    u = rays.mean(0)
    u /= np.linalg.norm(u)
    if (rays @ u).min() <= 1e-6:
        return frustum_sphere(camera, cam_from_world, reach)
    wfc_R = cam_from_world[:3, :3].T
    c = camera_centers(cam_from_world)
    pts = np.vstack([rays * reach, np.zeros(3)]) @ wfc_R.T + c
    return _min_radius(pts, c, wfc_R @ (reach * u) + c)


def project_inside(
    points: np.ndarray, camera: Camera, cam_from_world: np.ndarray, min_depth=0.0, max_depth=np.inf, margin_px=0.0
) -> np.ndarray:
    """Mask of points in front of a pinhole camera, inside its image and depth range."""
    uv, z = project(camera.K, cam_from_world, points, with_depth=True)
    u, v = uv[:, 0], uv[:, 1]
    ok = (z > max(min_depth, 1e-9)) & (z <= max_depth)
    return ok & (u >= margin_px) & (u <= camera.width - margin_px) & (v >= margin_px) & (v <= camera.height - margin_px)


def visible_mask(
    positions: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    view_dir: np.ndarray,
    view_angle: np.ndarray,
    depth_range: np.ndarray,
    limits: ViewLimits | None = None,
) -> np.ndarray:
    """The exact visibility test of :func:`visible_rows` on explicit arrays (no index): in front of
    the camera, inside the image (with the margin), within the distance range and the viewing-angle
    range each landmark was trained for."""
    limits = ViewLimits() if limits is None else limits
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    ok = project_inside(positions, camera, cam_from_world, margin_px=max(limits.image_margin_px, 0.0))
    c = camera_centers(cam_from_world)
    v = c - positions
    dist = np.linalg.norm(v, axis=1)
    cosang = np.sum(v * np.asarray(view_dir, np.float64), 1) / np.maximum(dist, 1e-12)
    ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    dr = np.asarray(depth_range, np.float64)
    ok &= ang <= np.asarray(view_angle, np.float64) + limits.angle_margin_deg
    ok &= (dist >= dr[:, 0] * limits.depth_scale[0]) & (dist <= dr[:, 1] * limits.depth_scale[1])
    return ok


def visible_rows(
    index: SpatialIndex,
    camera: Camera,
    cam_from_world: np.ndarray,
    view_dir: np.ndarray,
    view_angle: np.ndarray,
    depth_range: np.ndarray,
    limits: ViewLimits | None = None,
) -> np.ndarray:
    """Landmarks visible from a pose: in the frustum, within the distance range and the viewing
    angle range they were trained for (paper sec. 3.3). Returns sorted rows; equal to
    ``flatnonzero(visible_mask(all positions, ...))``, but in a map of more than ``_DIRECT_MAX``
    landmarks only those near the frustum are tested (KD-tree queries per reach tier)."""
    if len(index) == 0:
        return np.zeros(0, np.int64)
    limits = ViewLimits() if limits is None else limits
    depth_range = np.asarray(depth_range)
    view_dir = np.asarray(view_dir)
    view_angle = np.asarray(view_angle)
    tiers = index.prepare_visibility(depth_range, float(limits.depth_scale[1]), view_dir, view_angle)
    return tiers.visible(camera, cam_from_world, limits)
