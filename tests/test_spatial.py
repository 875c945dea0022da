"""Spatial index: radius / k-NN / frustum / visibility queries against numpy brute force, occlusion."""

from __future__ import annotations

import numpy as np
import pytest

from favormap import kdtree
from favormap.geometry import camera_centers, look_at, perturb_pose
from favormap.io import Camera
from favormap.ops.spatial import occluded
from favormap.visibility import (
    KD_BACKENDS,
    SpatialIndex,
    ViewLimits,
    frustum_sphere,
    reach_sphere,
    visible_mask,
    visible_rows,
)

BACKENDS = pytest.mark.parametrize("backend", sorted(KD_BACKENDS))  # auto, numpy, open3d, scipy


@pytest.fixture(params=["direct", "tiers"])
def visibility_path(request, monkeypatch):
    """Visibility queries through both paths: every landmark tested directly (maps up to
    favormap.visibility._DIRECT_MAX landmarks) and the reach tiers with their KD-trees (larger maps)."""
    import favormap.visibility as vis

    if request.param == "tiers":
        monkeypatch.setattr(vis, "_DIRECT_MAX", 0)
    return request.param


def assert_path(idx: SpatialIndex, path: str) -> None:
    """The index's visibility tiers took ``path`` (every landmark in the one directly tested group, or not)."""
    assert (idx._tiers.num_direct == len(idx)) == (path == "direct")


def brute_project(P, cam, T, min_depth=0.0, max_depth=np.inf, margin=0.0):
    """Independent brute-force projection test (COLMAP pixel convention: image = [0, W] x [0, H])."""
    Xc = P @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * Xc[:, 0] / z + cx
        v = fy * Xc[:, 1] / z + cy
    return (
        (z > max(min_depth, 1e-9))
        & (z <= max_depth)
        & (u >= margin)
        & (u <= cam.width - margin)
        & (v >= margin)
        & (v <= cam.height - margin)
    )


def brute_visible(P, vd, va, dr, cam, T, lim: ViewLimits):
    ok = brute_project(P, cam, T, margin=lim.image_margin_px)
    c = camera_centers(T)
    d = np.linalg.norm(c - P, axis=1)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", c - P, vd) / d, -1, 1)))
    ok &= ang <= va + lim.angle_margin_deg
    ok &= (d >= dr[:, 0] * lim.depth_scale[0]) & (d <= dr[:, 1] * lim.depth_scale[1])
    return np.flatnonzero(ok)


def random_pose(rng, scale=10.0):
    eye = rng.uniform(-scale, scale, 3)
    target = eye + rng.normal(size=3)
    return look_at(eye, target, up=(0, 0, 1) if rng.random() < 0.5 else (0, 1, 0))


@BACKENDS
def test_radius_and_knn_match_brute_force(backend):
    rng = np.random.default_rng(0)
    P = rng.uniform(-5, 5, (5000, 3))
    idx = SpatialIndex(P, backend=backend)
    for _ in range(20):
        c = rng.uniform(-6, 6, 3)
        r = rng.uniform(0.1, 3)
        d = np.linalg.norm(P - c, axis=1)
        np.testing.assert_array_equal(idx.radius(c, r), np.flatnonzero(d <= r))
        k = int(rng.integers(1, 30))
        rows, dist = idx.knn(c, k)
        np.testing.assert_allclose(dist, np.sort(d)[:k], rtol=1e-9)
        np.testing.assert_allclose(d[rows], dist, rtol=1e-9)
    # batched k-NN
    Q = rng.uniform(-6, 6, (300, 3))
    rows, dist = idx.knn_batch(Q, 4)
    D = np.linalg.norm(Q[:, None] - P[None], axis=2)
    np.testing.assert_allclose(dist, np.sort(D, 1)[:, :4], rtol=1e-6)
    np.testing.assert_allclose(np.take_along_axis(D, rows, 1), dist, rtol=1e-6)
    # more neighbours asked than points, and empty index
    small = SpatialIndex(P[:3], backend=backend)
    r, d = small.knn_batch(Q[:2], 5)
    assert (r[:, 3:] == -1).all() and np.isinf(d[:, 3:]).all()
    empty = SpatialIndex(np.zeros((0, 3)), backend=backend)
    assert len(empty.radius([0, 0, 0], 1)) == 0 and len(empty.knn([0, 0, 0], 3)[0]) == 0
    assert len(empty.frustum(Camera("PINHOLE", 10, 10, [5, 5, 5, 5]), np.eye(4), 10)) == 0


@BACKENDS
def test_frustum_equals_brute_force_projection_on_random_points(backend):
    rng = np.random.default_rng(1)
    P = rng.uniform(-10, 10, (40000, 3))
    idx = SpatialIndex(P, backend=backend)
    cams = [
        Camera("PINHOLE", 640, 480, [500, 500, 320, 240]),
        Camera("PINHOLE", 320, 240, [150, 160, 40, 200]),  # wide, off-centre principal point
        Camera("SIMPLE_PINHOLE", 100, 400, [900, 50, 200]),
    ]  # narrow
    n_nonempty = 0
    for i in range(40):
        cam = cams[i % len(cams)]
        T = random_pose(rng)
        max_depth = rng.uniform(0.5, 15)
        min_depth = 0.0 if i % 2 else rng.uniform(0, max_depth / 2)
        got = idx.frustum(cam, T, max_depth, min_depth)
        want = np.flatnonzero(brute_project(P, cam, T, min_depth, max_depth))
        np.testing.assert_array_equal(got, want)
        n_nonempty += len(want) > 0
    assert n_nonempty > 20
    # infinite depth: everything in front and inside the image
    T = random_pose(rng)
    np.testing.assert_array_equal(idx.frustum(cams[0], T, np.inf), np.flatnonzero(brute_project(P, cams[0], T)))


def test_frustum_sphere_encloses_the_frustum_and_is_tight():
    rng = np.random.default_rng(2)
    cam = Camera("PINHOLE", 640, 480, [500, 500, 320, 240])
    T = random_pose(rng)
    center, r = frustum_sphere(cam, T, 10.0)
    # random points inside the frustum
    u = rng.uniform(0, 640, 5000)
    v = rng.uniform(0, 480, 5000)
    z = rng.uniform(0, 10, 5000)
    Xc = np.c_[(u - 320) / 500 * z, (v - 240) / 500 * z, z]
    Xw = (Xc - T[:3, 3]) @ T[:3, :3]
    assert np.linalg.norm(Xw - center, axis=1).max() <= r + 1e-9
    far_corner = np.linalg.norm([320 / 500 * 10, 240 / 500 * 10, 10])
    assert r < 0.9 * far_corner  # smaller than the sphere around the camera centre


@pytest.mark.parametrize(
    "cam",
    [
        Camera("PINHOLE", 640, 480, [500, 500, 320, 240]),
        Camera("PINHOLE", 320, 240, [100, 120, 10, 230]),  # very wide, off-centre
        Camera("SIMPLE_PINHOLE", 100, 400, [900, 50, 200]),
    ],
)
def test_reach_sphere_encloses_the_view_pyramid_within_reach(cam):
    rng = np.random.default_rng(6)
    T = random_pose(rng)
    reach = 7.0
    center, r = reach_sphere(cam, T, reach)
    # points of the pyramid within ``reach`` of the camera, many on the boundary (corner rays, cap)
    n = 20000
    u = np.where(rng.random(n) < 0.3, rng.choice([0, cam.width], n), rng.uniform(0, cam.width, n))
    v = np.where(rng.random(n) < 0.3, rng.choice([0, cam.height], n), rng.uniform(0, cam.height, n))
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    d = np.c_[(u - cx) / fx, (v - cy) / fy, np.ones(n)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rho = np.where(rng.random(n) < 0.5, reach, rng.uniform(0, reach, n))
    Xw = (d * rho[:, None] - T[:3, 3]) @ T[:3, :3]
    assert np.linalg.norm(Xw - center, axis=1).max() <= r * (1 + 1e-9)
    assert r <= frustum_sphere(cam, T, reach)[1] + 1e-9  # never worse than the depth-cut frustum's


@BACKENDS
def test_visible_rows_equal_brute_force_on_the_small_map(small_map, backend, visibility_path):
    m, _ = small_map
    idx = SpatialIndex(m.positions, backend=backend)
    cam = m.cameras[0]
    rng = np.random.default_rng(3)
    limits = [ViewLimits(), ViewLimits(5.0, (0.8, 1.2), 10.0), ViewLimits(0.0, (1.0, 1.0), 0.0)]
    checked = 0
    for i, T0 in enumerate(m.cam_from_world):
        for lim in limits:
            T = perturb_pose(T0, 0.2, 10.0, rng) if i % 2 else T0
            got = visible_rows(idx, cam, T, m.view_dir, m.view_angle, m.depth_range, lim)
            want = brute_visible(m.positions, m.view_dir, m.view_angle, m.depth_range, cam, T, lim)
            np.testing.assert_array_equal(got, want)
            checked += len(want)
    assert checked > 1000
    assert_path(idx, visibility_path)
    # a training view sees most of what was triangulated from it
    T = m.cam_from_world[0]
    seen = np.unique(m.track_landmark[m.track_frame == 0])
    vis = visible_rows(idx, cam, T, m.view_dir, m.view_angle, m.depth_range)
    assert np.isin(seen, vis).mean() > 0.95


@BACKENDS
def test_visible_rows_exact_with_landmarks_of_very_different_reach(backend, visibility_path):
    """Most landmarks seen from ~2-5 units, 0.5 % from up to 200: the far ones bypass the KD-tree
    sphere (it would otherwise cover everything), and the result is still exact."""
    rng = np.random.default_rng(4)
    P, vd, va, dr = random_landmarks(rng, 20000, 50, far_reach=(50, 200))
    idx = SpatialIndex(P, backend=backend)
    cam = Camera("PINHOLE", 640, 480, [400, 400, 320, 240])
    total = 0
    for _ in range(30):
        T = random_pose(rng, 50)
        got = visible_rows(idx, cam, T, vd, va, dr)
        want = brute_visible(P, vd, va, dr, cam, T, ViewLimits())
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(got, np.flatnonzero(visible_mask(P, cam, T, vd, va, dr)))
        total += len(want)
    assert total > 0
    assert_path(idx, visibility_path)
    # the cached tiers follow new arrays (another depth range, other view directions)
    T = random_pose(rng, 50)
    for dr2, vd2 in ((dr * 0.5, vd), (dr, -vd)):
        np.testing.assert_array_equal(
            visible_rows(idx, cam, T, vd2, va, dr2), brute_visible(P, vd2, va, dr2, cam, T, ViewLimits())
        )
    lim = ViewLimits(depth_scale=(0.1, 5.0))
    np.testing.assert_array_equal(visible_rows(idx, cam, T, vd, va, dr, lim), brute_visible(P, vd, va, dr, cam, T, lim))


def test_occlusion_by_a_mesh():
    import trimesh

    cam_c = np.zeros(3)
    wall = trimesh.creation.box(extents=[2, 2, 0.01])
    wall.apply_translation([0, 0, 5])  # a thin wall at z = 5 covering |x|, |y| < 1
    P = np.array([[0, 0, 10.0], [0.5, 0.5, 8], [3, 0, 10], [0, 0, 4.0], [0, 0, 4.995]])
    hid = occluded(P, cam_c, wall)
    assert hid.tolist() == [True, True, False, False, False]
    # a landmark on the surface (within tolerance) is not hidden by that surface
    assert not occluded(np.array([[0, 0, 5.01]]), cam_c, wall, tolerance=0.05)[0]
    # Open3D meshes and scenes work too
    import open3d as o3d

    o3m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(wall.vertices), o3d.utility.Vector3iVector(wall.faces))
    assert occluded(P, cam_c, o3m).tolist() == hid.tolist()
    assert occluded(P, cam_c, trimesh.Scene([wall])).tolist() == hid.tolist()


@BACKENDS
@pytest.mark.parametrize("n", [1, 999, 2500])
def test_visible_rows_small_and_degenerate_maps(n, backend, visibility_path):
    rng = np.random.default_rng(n)
    P = rng.uniform(-1, 1, (n, 3)) + [0, 0, 3]
    vd = np.tile([0, 0, -1.0], (n, 1))
    dr = np.tile([1.0, 4.0], (n, 1))
    va = np.full(n, 30.0)
    cam = Camera("PINHOLE", 64, 48, [40, 40, 32, 24])
    idx = SpatialIndex(P, backend=backend)
    got = visible_rows(idx, cam, np.eye(4), vd, va, dr)
    np.testing.assert_array_equal(got, brute_visible(P, vd, va, dr, cam, np.eye(4), ViewLimits()))
    assert_path(idx, visibility_path)


def random_landmarks(rng, L, extent, far_reach=(20, 60)):
    """Random positions, view directions, view angles and depth ranges (0.5 % seen from as far as
    ``far_reach``)."""
    P = rng.uniform(-extent, extent, (L, 3))
    vd = rng.normal(size=(L, 3))
    vd /= np.linalg.norm(vd, axis=1, keepdims=True)
    va = rng.uniform(10, 60, L).astype(np.float32)
    lo = rng.uniform(1, 3, L)
    dr = np.c_[lo, lo + rng.uniform(0.5, 3, L)].astype(np.float32)
    far = rng.random(L) < 0.005
    dr[far, 1] = rng.uniform(*far_reach, far.sum())
    return P, vd, va, dr


def test_numpy_scan_returns_the_same_rows_as_scipy(monkeypatch):
    """The brute-force backend against cKDTree: identical radius rows (also for radii at a point's
    distance, where rounding decides), k-NN rows and distances, frustum and visibility rows (through
    the reach tiers, which the 6,000 landmarks would otherwise skip)."""
    import favormap.visibility as vis

    monkeypatch.setattr(vis, "_DIRECT_MAX", 0)
    rng = np.random.default_rng(7)
    P, vd, va, dr = random_landmarks(rng, 6000, 15.0)
    scan, tree = SpatialIndex(P, backend="numpy"), SpatialIndex(P, backend="scipy")
    assert isinstance(scan._tree, kdtree._NumpyScan) and isinstance(tree._tree, kdtree._ScipyTree)
    for i in range(40):
        c = rng.uniform(-16, 16, 3)
        r = rng.uniform(0.1, 8) if i % 2 else float(np.sqrt(np.sum((P[i] - c) ** 2)))  # on a point
        np.testing.assert_array_equal(scan.radius(c, r), tree.radius(c, r))
        for k in (1, 7):
            np.testing.assert_array_equal(scan.knn(c, k)[0], tree.knn(c, k)[0])
            np.testing.assert_array_equal(scan.knn(c, k)[1], tree.knn(c, k)[1])
    Q = rng.uniform(-16, 16, (700, 3))
    for k in (1, 5, 6001):
        (r1, d1), (r2, d2) = scan.knn_batch(Q, k), tree.knn_batch(Q, k)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(d1, d2)
    cam = Camera("PINHOLE", 640, 480, [400, 400, 320, 240])
    for _ in range(20):
        T = random_pose(rng, 15)
        depth = rng.uniform(1, 20)
        np.testing.assert_array_equal(scan.frustum(cam, T, depth), tree.frustum(cam, T, depth))
        np.testing.assert_array_equal(visible_rows(scan, cam, T, vd, va, dr), visible_rows(tree, cam, T, vd, va, dr))
    assert len(scan.prepare_visibility(dr, 2.0, vd, va).tiers) > 1  # several trees were compared


def test_numpy_scan_knn_ties_and_chunks(monkeypatch):
    """Duplicated points: the distances equal cKDTree's, tied rows come lowest first (a stable
    sort by distance); a tiny chunk size (many chunks) changes nothing."""
    rng = np.random.default_rng(8)
    P = np.repeat(rng.uniform(-1, 1, (40, 3)), 3, axis=0)
    P[::7] = P[0]  # one point many times: ties across the k-th neighbour
    Q = np.vstack([rng.uniform(-1, 1, (200, 3)), P[:5]])
    scan = SpatialIndex(P, backend="numpy")
    D2 = np.sum((Q[:, None] - P[None]) ** 2, axis=2)
    for k in (1, 2, 4, 17):
        rows, dist = scan.knn_batch(Q, k)
        np.testing.assert_array_equal(dist, SpatialIndex(P, backend="scipy").knn_batch(Q, k)[1])
        np.testing.assert_array_equal(rows, np.argsort(D2, axis=1, kind="stable")[:, :k])
        monkeypatch.setattr(kdtree, "_SCAN_CHUNK_BYTES", 100)
        small = SpatialIndex(P, backend="numpy")
        np.testing.assert_array_equal(small.knn_batch(Q, k)[0], rows)
        np.testing.assert_array_equal(small.radius(Q[0], 0.5), scan.radius(Q[0], 0.5))
        monkeypatch.undo()


def test_auto_backend_picks_the_scan_for_small_trees(monkeypatch):
    """ "auto" (the default) scans up to BRUTE_FORCE_MAX points and builds a cKDTree above, deciding
    per tree: each visibility tier on its own size. Explicit backends are kept whatever the size."""
    import favormap.visibility as vis

    assert SpatialIndex(np.zeros((3, 3))).backend == "auto"
    assert 20_000 <= kdtree.BRUTE_FORCE_MAX <= 200_000
    monkeypatch.setattr(kdtree, "BRUTE_FORCE_MAX", 1000)
    monkeypatch.setattr(vis, "_DIRECT_MAX", 0)  # the reach tiers of a map larger than it
    rng = np.random.default_rng(9)
    P, vd, va, dr = random_landmarks(rng, 5000, 10.0)
    assert isinstance(SpatialIndex(P[:1000])._tree, kdtree._NumpyScan)
    assert isinstance(SpatialIndex(P[:1001])._tree, kdtree._ScipyTree)
    assert isinstance(SpatialIndex(P[:10], backend="scipy")._tree, kdtree._ScipyTree)
    assert isinstance(SpatialIndex(P[:10], backend="open3d")._tree, kdtree._Open3DTree)
    assert isinstance(SpatialIndex(P, backend="numpy")._tree, kdtree._NumpyScan)
    idx = SpatialIndex(P)
    tiers = [t for t in idx.prepare_visibility(dr, 2.0, vd, va).tiers if t["tree"] is not None]
    kinds = {isinstance(t["tree"], kdtree._NumpyScan) for t in tiers}
    assert kinds == {True, False}  # tiers of both sizes here
    for t in tiers:
        want = kdtree._NumpyScan if len(t["rows"]) <= 1000 else kdtree._ScipyTree
        assert type(t["tree"]) is want
    cam = Camera("PINHOLE", 640, 480, [400, 400, 320, 240])
    for _ in range(10):
        T = random_pose(rng, 10)
        want = brute_visible(P, vd, va, dr, cam, T, ViewLimits())
        np.testing.assert_array_equal(visible_rows(idx, cam, T, vd, va, dr), want)


def test_small_maps_do_not_import_scipy_spatial():
    """Importing scipy.spatial costs ~0.5 s of a one-shot localization: a small index (the default
    "auto" backend) answers radius, k-NN, frustum and visibility queries without it."""

    code = (
        "import sys, numpy as np\n"
        "from favormap.io import Camera\n"
        "from favormap.visibility import SpatialIndex, visible_rows\n"
        "rng = np.random.default_rng(0)\n"
        "L = 1000\n"
        "P = rng.uniform(-1, 1, (L, 3)) + [0, 0, 3]\n"
        "vd = np.tile([0, 0, -1.0], (L, 1))\n"
        "dr = np.tile([1.0, 4.0], (L, 1))\n"
        "idx = SpatialIndex(P)\n"
        "cam = Camera('PINHOLE', 64, 48, [40, 40, 32, 24])\n"
        "n = [len(idx.radius([0, 0, 3], 0.5)), len(idx.knn([0, 0, 3], 5)[0]), len(idx.frustum(cam, np.eye(4), 5))]\n"
        "n.append(len(visible_rows(idx, cam, np.eye(4), vd, np.full(L, 30.0), dr)))\n"
        "print(*n, 'scipy.spatial' in sys.modules)\n"
    )
    out = _run_child(code)
    *n, imported = out.stdout.split()
    assert all(int(x) > 0 for x in n), out.stdout
    assert imported == "False"


def _run_child(code: str):
    """Run ``code`` in a fresh interpreter (import side effects are per process); it must succeed."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="unknown KD-tree backend"):
        SpatialIndex(np.zeros((3, 3)), backend="flann")


def test_localization_path_does_not_import_open3d(small_map):
    """The build / localize core runs where Open3D is not installed (e.g. a GPU machine)."""

    code = (
        "import sys, numpy as np\n"
        "sys.modules['open3d'] = None\n"  # any import of open3d now fails
        "from favormap.localize import Localizer\n"
        "import favormap.build, favormap.localize.evaluate\n"
        f"loc = Localizer({str(small_map[1])!r})\n"
        "from favormap.visibility import visible_rows\n"
        "T = loc.map.cam_from_world[0]\n"
        "cam = next(iter(loc.map.cameras.values()))\n"
        "print(len(visible_rows(loc.index, cam, T, loc.map.view_dir, loc.map.view_angle, loc.map.depth_range)))\n"
    )
    out = _run_child(code)
    assert int(out.stdout.split()[-1]) > 0
