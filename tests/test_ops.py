"""Map operations: merge, prune, export, query, their CLI commands and failure modes."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest

from favormap.errors import IncompatibleMapsError, MapFormatError
from favormap.geometry import camera_centers, inverse, rotation_about
from favormap.mapfile import Map, check_file, write_map


# -- helpers ------------------------------------------------------------------------------------------
def check_written_map(path):
    """Schema-valid, consistent tracks, unique ids. Returns the loaded MapData."""
    with h5py.File(path, "r") as f:
        assert check_file(f) == []
    with Map.open(path) as m:
        d = m.load()
    assert len(np.unique(d.ids)) == d.num_landmarks
    np.testing.assert_array_equal(np.bincount(d.track_landmark, minlength=d.num_landmarks), d.track_length)
    assert d.track_frame.max(initial=-1) < d.num_frames
    assert set(np.unique(d.frame_camera_ids)) <= set(d.cameras)
    return d


def one_error_line(capsys):
    cap = capsys.readouterr()
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert len(lines) == 1, cap.err
    assert "Traceback" not in cap.err and "error" in lines[0]
    return lines[0]


def write_variant(m, path, **changes):
    write_map(dataclasses.replace(m, **changes), path)
    return path


def moved_copy(m, T_b_to_a):
    """``m`` (frame a) expressed in frame b, where x_a = T x_b (T a similarity s*R|t)."""
    from favormap.ops.merge import resample_matrix

    s = float(np.cbrt(np.linalg.det(T_b_to_a[:3, :3])))
    R = T_b_to_a[:3, :3] / s
    Tinv = np.linalg.inv(T_b_to_a)
    pos = m.positions @ Tinv[:3, :3].T + Tinv[:3, 3]
    cfw = m.cam_from_world @ T_b_to_a
    cfw[:, :3, :] /= s
    res = m.grid_resolution
    W = resample_matrix(R.T, res)
    W = np.eye(res**3) if W is None else W
    L, C = m.num_landmarks, m.channels
    desc = np.einsum("nr,brc->bnc", W, m.descriptors.reshape(L, res**3, C)).reshape(m.descriptors.shape)
    dens = (m.density.reshape(L, -1) @ W.T).reshape(m.density.shape)
    return dataclasses.replace(
        m,
        positions=pos,
        view_dir=(m.view_dir @ R).astype(np.float32),
        voxel_size=(m.voxel_size / s).astype(np.float32),
        depth_range=(m.depth_range / s).astype(np.float32),
        cam_from_world=cfw,
        descriptors=desc.astype(np.float32),
        density=dens.astype(np.float32),
    )


def voxels_of(path, rows=None):
    with Map.open(path) as m:
        rows = np.arange(len(m)) if rows is None else rows
        return m.voxels(rows)


# -- streaming writer ---------------------------------------------------------------------------------
def write_streaming(m, path, chunk=37, nan_at=None):
    from favormap.mapfile.writer import MapWriter
    from favormap.ops.rewrite import write_frames_and_tracks, write_landmark_metadata

    header = {k: getattr(m, k) for k in MapWriter.HEADER_KEYS}
    header["provenance"] = m.provenance
    L = m.num_landmarks
    with MapWriter(path, header, L, m.num_frames) as w:
        write_landmark_metadata(w, {k: getattr(m, k) for k in m.landmark_names()})
        write_frames_and_tracks(
            w,
            m.cameras,
            m.frame_names,
            m.frame_camera_ids,
            m.cam_from_world,
            m.track_landmark,
            m.track_frame,
            m.track_xy,
        )
        for k in ("voxels/descriptors", "voxels/density", "landmarks/mean_descriptor"):
            w.create(k)
        for a in range(0, L, chunk):
            d = m.descriptors[a : a + chunk].copy()
            if nan_at is not None and a <= nan_at < a + chunk:
                d[nan_at - a] = np.nan
            w.write_rows("voxels/descriptors", a, d)
            w.write_rows("voxels/density", a, m.density[a : a + chunk])
            w.write_rows("landmarks/mean_descriptor", a, m.mean_descriptor[a : a + chunk])


def test_streaming_writer_matches_write_map_and_refuses_bad_values(small_map, tmp_path):
    m, path = small_map
    write_streaming(m, tmp_path / "s.h5")
    d = check_written_map(tmp_path / "s.h5")
    with h5py.File(path, "r") as f, h5py.File(tmp_path / "s.h5", "r") as g:
        for name in ("voxels/descriptors", "voxels/density", "landmarks/mean_descriptor", "tracks/xy", "frames/names"):
            assert f[name].dtype == g[name].dtype and f[name].chunks == g[name].chunks
            np.testing.assert_array_equal(f[name][()], g[name][()])
        assert {k: f.attrs[k] for k in f.attrs if k != "created"} == {k: g.attrs[k] for k in g.attrs if k != "created"}
    np.testing.assert_array_equal(d.ids, m.ids)
    # a NaN in a streamed block: refused, nothing (not even a partial file) left behind
    with pytest.raises(MapFormatError, match="not finite"):
        write_streaming(m, tmp_path / "bad.h5", nan_at=100)
    assert not (tmp_path / "bad.h5").exists() and not list(tmp_path.glob(".bad.h5*"))
    with pytest.raises(MapFormatError, match="duplicated"):
        write_streaming(dataclasses.replace(m, ids=np.r_[m.ids[:-1], m.ids[:1]]), tmp_path / "bad.h5")
    assert not (tmp_path / "bad.h5").exists()


# -- merge --------------------------------------------------------------------------------------------
def test_merging_a_map_with_itself_keeps_its_landmarks(small_map, tmp_path):
    from favormap.ops.merge import merge_maps

    m, path = small_map
    out = tmp_path / "self.h5"
    res = merge_maps([path, path], out, chunk=64)
    d = check_written_map(out)
    assert res.num_landmarks == d.num_landmarks == m.num_landmarks
    np.testing.assert_array_equal(d.ids, m.ids)
    assert res.sources[1]["dropped_duplicates"] == m.num_landmarks
    assert d.num_frames == 2 * m.num_frames and len(d.cameras) == 1  # one camera, shared
    assert len(set(d.frame_names)) == d.num_frames  # colliding names were prefixed
    np.testing.assert_array_equal(d.frame_camera_ids, 0)
    np.testing.assert_array_equal(d.track_landmark, m.track_landmark)
    np.testing.assert_allclose(d.descriptors, m.descriptors, atol=2e-3)
    np.testing.assert_array_equal(d.density, m.density)
    prov = json.loads(h5py.File(out, "r").attrs["provenance"])
    assert [s["path"] for s in prov["merge"]["sources"]] == [str(path), str(path)]


def test_merge_shares_equal_cameras_and_keeps_different_ones(small_map, tmp_path):
    from favormap.io.types import Camera
    from favormap.ops.merge import merge_maps

    m, path = small_map
    assert len(m.cameras) == 1
    cam = m.cameras[0]
    zoomed = Camera(cam.model, cam.width, cam.height, cam.params * np.r_[1.01, np.ones(len(cam.params) - 1)])
    write_streaming(dataclasses.replace(m, cameras={0: zoomed}), tmp_path / "b.h5")
    merge_maps([path, path, tmp_path / "b.h5"], tmp_path / "m.h5", chunk=64)
    d = check_written_map(tmp_path / "m.h5")
    assert len(d.cameras) == 2 and d.num_frames == 3 * m.num_frames
    F = m.num_frames
    np.testing.assert_array_equal(d.frame_camera_ids, np.r_[np.zeros(2 * F), np.ones(F)])
    assert d.cameras[0].params.tolist() == cam.params.tolist()
    assert d.cameras[1].params.tolist() == zoomed.params.tolist()


def test_merge_keeps_the_better_duplicate_and_unique_ids(small_map, tmp_path):
    from favormap.ops.merge import merge_maps

    m, path = small_map
    rng = np.random.default_rng(0)
    better = np.arange(m.num_landmarks) % 2 == 0
    q = m.quality.copy()
    q[better] += 1.0
    jitter = rng.normal(size=m.positions.shape)
    # each copy moved by 0.2 voxel sides, and by less than half the way to its landmark's nearest neighbour
    # (some lie 0.3 voxel sides apart), so that it duplicates its own landmark and no other
    from scipy.spatial import cKDTree

    nn_dist = cKDTree(m.positions).query(m.positions, k=2)[0][:, 1]
    step = np.minimum(0.2 * m.voxel_size, 0.4 * nn_dist)
    jitter *= step[:, None] / np.linalg.norm(jitter, axis=1, keepdims=True)
    b = write_variant(m, tmp_path / "b.h5", quality=q, positions=m.positions + jitter)
    res = merge_maps([path, b], tmp_path / "m.h5")
    d = check_written_map(tmp_path / "m.h5")
    assert d.num_landmarks == m.num_landmarks
    assert res.sources[1]["replaced"] == better.sum()
    # every landmark kept with the better quality, and each replaced one keeps its own observations
    np.testing.assert_allclose(np.sort(d.quality), np.sort(q))
    from_b = d.track_frame >= m.num_frames
    assert np.unique(d.track_landmark[from_b]).size == better.sum()


def test_merge_without_overlap_keeps_all_and_regenerates_colliding_ids(small_map, tmp_path):
    from favormap.ops.merge import merge_maps

    m, path = small_map
    T = np.eye(4)
    T[0, 3] = 100.0
    far = dataclasses.replace(moved_copy(m, inverse(T)))  # same map, 100 units away, same ids
    write_map(far, tmp_path / "far.h5")
    res = merge_maps([path, tmp_path / "far.h5"], tmp_path / "m.h5", chunk=50)
    d = check_written_map(tmp_path / "m.h5")
    L = m.num_landmarks
    assert d.num_landmarks == 2 * L and res.ids_regenerated == L
    np.testing.assert_array_equal(d.ids[:L], m.ids)
    np.testing.assert_allclose(d.positions[L:], m.positions + [100, 0, 0], atol=1e-9)
    np.testing.assert_array_equal(d.density[L:], d.density[:L])
    np.testing.assert_array_equal(d.track_length[L:], m.track_length)


@pytest.mark.parametrize("scale", [1.0, 2.0])
def test_merge_with_a_transform_file_maps_the_second_map_back(small_map, tmp_path, scale):
    """Map b is map a's second half expressed in another frame (rotated 90 deg about z, shifted,
    scaled); merging with --transform b_to_a restores positions, poses and voxel grids."""
    from favormap.cli import main

    m, path = small_map
    T = np.eye(4)
    T[:3, :3] = scale * rotation_about([0, 0, 1], np.pi / 2)
    T[:3, 3] = [0.5, -1.0, 2.0]
    np.savetxt(tmp_path / "b_to_a.txt", T)
    L = m.num_landmarks
    half = np.arange(L // 2, L)
    write_map(m.select_landmarks(np.arange(L // 2)), tmp_path / "a.h5")
    write_map(moved_copy(m.select_landmarks(half), T), tmp_path / "b.h5")
    # (nearby landmarks of one map may look like duplicates: no dedup, to compare everything)
    assert (
        main(
            [
                "merge",
                str(tmp_path / "a.h5"),
                str(tmp_path / "b.h5"),
                "-o",
                str(tmp_path / "m.h5"),
                "--transform",
                str(tmp_path / "b_to_a.txt"),
                "--json",
                "-q",
                "--no-dedup",
            ]
        )
        == 0
    )
    d = check_written_map(tmp_path / "m.h5")
    assert d.num_landmarks == L
    np.testing.assert_allclose(d.positions, m.positions, atol=1e-9)
    np.testing.assert_allclose(d.view_dir, m.view_dir, atol=1e-6)
    np.testing.assert_allclose(d.voxel_size, m.voxel_size, rtol=1e-6)
    np.testing.assert_allclose(d.depth_range, m.depth_range, rtol=1e-6)
    np.testing.assert_allclose(d.cam_from_world[m.num_frames :], m.cam_from_world, atol=1e-9)
    np.testing.assert_allclose(d.descriptors, m.descriptors, atol=2e-3)  # 90 deg: exact node permutation
    np.testing.assert_allclose(d.density, m.density, rtol=1e-6)
    # the whole map in frame b merged onto itself in frame a: every landmark is found as a duplicate
    write_map(moved_copy(m, T), tmp_path / "b_all.h5")
    assert (
        main(
            [
                "merge",
                str(path),
                str(tmp_path / "b_all.h5"),
                "-o",
                str(tmp_path / "m2.h5"),
                "--transform",
                str(tmp_path / "b_to_a.txt"),
                "-q",
            ]
        )
        == 0
    )
    d = check_written_map(tmp_path / "m2.h5")
    assert d.num_landmarks == L
    np.testing.assert_array_equal(d.ids, m.ids)


def test_grid_resampling_reproduces_linear_fields():
    """A descriptor grid holding a linear function of position is resampled exactly under a 90
    degree rotation (nodes land on nodes) and keeps its centre value under any rotation."""
    import itertools

    from favormap.ops.merge import resample_matrix

    res = 3
    g = np.arange(res) / (res - 1) - 0.5
    nodes = np.array(list(itertools.product(g, g, g)))  # (x, y, z) order, x slowest
    a = np.array([1.0, -2.0, 0.5])
    field_b = nodes @ a
    for R in (rotation_about([0, 0, 1], np.pi / 2), rotation_about([1, 0, 0], -np.pi / 2)):
        W = resample_matrix(R, res)
        np.testing.assert_allclose(W @ field_b, nodes @ R @ a, atol=1e-6)  # f_a(p) = f_b(R^T p)
    W = resample_matrix(rotation_about([1, 1, 0], 0.3), res)
    assert W[res**3 // 2, res**3 // 2] == pytest.approx(1.0)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-6)
    assert resample_matrix(np.eye(3), res) is None


def test_merge_refuses_incompatible_maps(small_map, tmp_path):
    from favormap.ops.merge import merge_maps

    m, path = small_map
    c32 = write_variant(
        m,
        tmp_path / "c32.h5",
        channels=32,
        descriptors=m.descriptors[..., :32],
        mean_descriptor=m.mean_descriptor[:, :32],
    )
    with pytest.raises(IncompatibleMapsError) as e:
        merge_maps([path, c32], tmp_path / "x.h5")
    assert "channels" in str(e.value) and str(m.channels) in str(e.value) and "32" in str(e.value)
    other_name = "xfeat" if m.extractor == "sift" else "sift"
    other = write_variant(m, tmp_path / "other.h5", extractor=other_name)
    with pytest.raises(IncompatibleMapsError, match=rf"extractor \('{m.extractor}' vs '{other_name}'\)"):
        merge_maps([path, other], tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()
    assert not list(tmp_path.glob(".x.h5*"))  # no partial file left


# -- prune --------------------------------------------------------------------------------------------
def test_prune_to_a_budget_keeps_coverage(small_map, tmp_path):
    from favormap.ops.prune import prune_map

    m, path = small_map
    N = 60
    res = prune_map(path, tmp_path / "p.h5", max_landmarks=N, chunk=16)
    d = check_written_map(tmp_path / "p.h5")
    assert d.num_landmarks <= N and res.num_after == d.num_landmarks >= N - 1
    assert res.removed["budget"] == m.num_landmarks - d.num_landmarks
    ext0 = m.positions.max(0) - m.positions.min(0)
    ext1 = d.positions.max(0) - d.positions.min(0)
    assert np.all(ext1 >= 0.8 * ext0), (ext1, ext0)

    def coarse(P, lo, ext, n=3):
        return set(map(tuple, np.minimum(((P - lo) / ext * n).astype(int), n - 1)))

    lo = m.positions.min(0)
    before, after = coarse(m.positions, lo, ext0), coarse(d.positions, lo, ext0)
    assert len(after) >= 0.9 * len(before), (len(after), len(before))
    # kept landmarks carry their data: ids, voxels, observations
    rows = np.flatnonzero(np.isin(m.ids, d.ids))
    np.testing.assert_array_equal(m.ids[rows], d.ids)
    np.testing.assert_allclose(d.descriptors, m.descriptors[rows], atol=2e-3)
    np.testing.assert_array_equal(d.track_length, m.track_length[rows])


def test_spatially_even_selection_keeps_sparse_regions():
    from favormap.ops.prune import spatially_even

    rng = np.random.default_rng(0)
    dense = rng.normal(0, 0.05, (5000, 3))
    sparse = rng.uniform(-10, 10, (100, 3))
    P = np.vstack([dense, sparse])
    q = np.r_[rng.uniform(30, 40, 5000), rng.uniform(20, 25, 100)]  # the dense cluster is better
    rows = spatially_even(P, q, 200)
    assert len(rows) == 200 and len(np.unique(rows)) == 200
    assert np.sum(rows >= 5000) >= 80  # most of the sparse region survives
    assert len(spatially_even(P, q, 10**6)) == len(P)


def test_prune_filters_by_track_quality_and_bbox(small_map, tmp_path, capsys):
    from favormap.cli import main

    m, path = small_map
    k, q = 8, float(np.median(m.quality))
    lo, hi = m.positions.min(0), m.positions.max(0)
    mid = (lo + hi) / 2
    bbox = ",".join(f"{v:.6f}" for v in np.r_[lo - 1, mid[0], hi[1:] + 1])
    out = tmp_path / "f.h5"
    assert (
        main(
            [
                "prune",
                str(path),
                "-o",
                str(out),
                "--min-track",
                str(k),
                "--min-quality",
                str(q),
                "--bbox",
                bbox,
                "--json",
            ]
        )
        == 0
    )
    s = json.loads(capsys.readouterr().out)
    d = check_written_map(out)
    P = m.positions
    keep = (m.track_length >= k) & (m.quality >= q) & np.all((P >= lo - 1) & (P <= np.r_[mid[0], hi[1:] + 1]), axis=1)
    np.testing.assert_array_equal(d.ids, m.ids[keep])
    assert d.num_frames == m.num_frames
    assert s["num_after"] == keep.sum() and sum(s["removed"].values()) == m.num_landmarks - keep.sum()
    assert s["failing"]["min_track"] == np.sum(m.track_length < k)


def test_prune_cli_reports_reasons_and_refuses_empty_results(small_map, tmp_path, capsys):
    from favormap.cli import main

    m, path = small_map
    out = tmp_path / "p.h5"
    assert main(["prune", str(path), "-o", str(out), "--min-track", "6", "--max-landmarks", "50", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["num_before"] == m.num_landmarks and s["num_after"] <= 50
    assert s["removed"]["min_track"] == int(np.sum(m.track_length < 6))
    assert s["removed"]["min_track"] + s["removed"]["budget"] == s["num_before"] - s["num_after"]
    assert main(["prune", str(path), "-o", str(out), "--max-landmarks", "50", "-q"]) == 0
    text = capsys.readouterr().out
    assert "kept" in text and "max-landmarks" in text
    # nothing left: error, nothing written
    assert main(["prune", str(path), "-o", str(tmp_path / "e.h5"), "--bbox", "100,100,100,101,101,101", "-q"]) != 0
    assert "would remove all" in one_error_line(capsys)
    assert not (tmp_path / "e.h5").exists()
    assert main(["prune", str(path), "-o", str(tmp_path / "e.h5"), "--bbox", "1,2,3", "-q"]) != 0
    assert "--bbox" in one_error_line(capsys)


# -- export -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ext", ["ply", "obj", "glb"])
def test_export_loads_back_in_trimesh(small_map, tmp_path, ext):
    import trimesh

    from favormap.ops.export import export_landmarks

    m, path = small_map
    L = m.num_landmarks

    def geoms(f):
        g = trimesh.load(f, process=False)
        return list(g.geometry.values()) if isinstance(g, trimesh.Scene) else [g]

    res = export_landmarks(path, tmp_path / f"p.{ext}")
    (g,) = geoms(tmp_path / f"p.{ext}")
    assert isinstance(g, trimesh.PointCloud) and len(g.vertices) == L == res.num_points
    np.testing.assert_allclose(np.sort(g.vertices[:, 0]), np.sort(m.positions[:, 0]), atol=1e-5)
    res = export_landmarks(path, tmp_path / f"b.{ext}", boxes=True, color_by="track")
    gs = geoms(tmp_path / f"b.{ext}")
    meshes = [x for x in gs if isinstance(x, trimesh.Trimesh)]
    assert len(meshes) == 1 and len(meshes[0].vertices) == 8 * L and len(meshes[0].faces) == 12 * L
    ext_box = np.ptp(np.asarray(meshes[0].vertices).reshape(L, 8, 3), axis=1)
    np.testing.assert_allclose(ext_box, np.repeat(m.voxel_size[:, None], 3, 1), rtol=1e-4)
    if ext == "glb":
        assert sum(isinstance(x, trimesh.PointCloud) for x in gs) == 1


def test_export_cli_and_errors(small_map, tmp_path, capsys):
    import trimesh

    from favormap.cli import main

    m, path = small_map
    assert main(["export", str(path), "-o", str(tmp_path / "l.ply"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["num_points"] == m.num_landmarks
    colors = trimesh.load(tmp_path / "l.ply").colors
    assert colors.shape == (m.num_landmarks, 4) and len(np.unique(colors[:, :3], axis=0)) > 10
    assert main(["export", str(path), "-o", str(tmp_path / "l.xyz")]) != 0
    assert "must end in" in one_error_line(capsys)
    assert main(["export", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "l.ply")]) != 0
    assert "not found" in one_error_line(capsys)


# -- query --------------------------------------------------------------------------------------------
def brute_visible_ids(m, cam, T, angle_margin=15.0, depth_scale=(0.5, 2.0)):
    P = m.positions
    Xc = P @ T[:3, :3].T + T[:3, 3]
    z = Xc[:, 2]
    K = cam.K
    u = K[0, 0] * Xc[:, 0] / np.where(z > 0, z, 1) + K[0, 2]
    v = K[1, 1] * Xc[:, 1] / np.where(z > 0, z, 1) + K[1, 2]
    c = camera_centers(T)
    dist = np.linalg.norm(c - P, axis=1)
    ang = np.degrees(np.arccos(np.clip(np.sum((c - P) * m.view_dir, 1) / dist, -1, 1)))
    ok = (z > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
    ok &= (
        (ang <= m.view_angle + angle_margin)
        & (dist >= m.depth_range[:, 0] * depth_scale[0])
        & (dist <= m.depth_range[:, 1] * depth_scale[1])
    )
    return m.ids[ok]


def test_query_cli_pose_json_matches_brute_force(small_map, tmp_path, capsys):
    from favormap.cli import main
    from favormap.geometry import perturb_pose
    from favormap.io.posefile import write_pose

    m, path = small_map
    rng = np.random.default_rng(5)
    for i in (0, 7, 13):
        T = perturb_pose(m.cam_from_world[i], 0.15, 8.0, rng)
        write_pose(tmp_path / "pose.txt", T)
        assert main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        want = brute_visible_ids(m, m.cameras[0], T)
        assert out["visible_ids"] == [int(x) for x in want] and out["num_visible"] == len(want) > 50
        assert out["num_landmarks"] == m.num_landmarks and out["num_occluded"] == 0
    # a narrower camera given as JSON sees a subset; human output lists ids
    cam = {"model": "PINHOLE", "width": 160, "height": 120, "params": [277.1, 277.1, 80, 60]}
    assert main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--camera", json.dumps(cam), "--json"]) == 0
    narrow = json.loads(capsys.readouterr().out)["visible_ids"]
    assert 0 < len(narrow) < len(want) and set(narrow) <= set(int(x) for x in want)
    assert main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--limit", "3"]) == 0
    text = capsys.readouterr().out
    assert "visible" in text and "more" in text


def test_query_cli_near_radius_and_knn(small_map, capsys):
    from favormap.cli import main

    m, path = small_map
    c = m.positions.mean(0)
    d = np.linalg.norm(m.positions - c, axis=1)
    r = float(np.sort(d)[25:27].mean())  # not on a landmark
    assert main(["query", str(path), "--near", *map(str, c), "--radius", str(r), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert sorted(out["ids"]) == sorted(int(x) for x in m.ids[d <= r]) and out["count"] >= 25
    assert out["distances"] == sorted(out["distances"])
    assert main(["query", str(path), "--near", *map(str, c), "--knn", "5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ids"] == [int(x) for x in m.ids[np.argsort(d)[:5]]]
    # nothing there: exit status 1, the (empty) answer is still printed
    assert main(["query", str(path), "--near", "100", "100", "100", "--radius", "1", "--json"]) == 1
    cap = capsys.readouterr()
    assert json.loads(cap.out)["count"] == 0 and len(cap.err.strip().splitlines()) == 1


def test_query_cli_with_a_mesh(small_map, tmp_path, capsys):
    import trimesh

    from favormap.cli import main
    from favormap.io.posefile import write_pose
    from favormap.synthetic import make_room

    m, path = small_map
    T = m.cam_from_world[2]
    write_pose(tmp_path / "pose.txt", T)
    room = make_room(0)
    trimesh.Trimesh(room.vertices, room.triangles, process=False).export(tmp_path / "room.ply")
    assert main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--json"]) == 0
    free = json.loads(capsys.readouterr().out)
    assert (
        main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--mesh", str(tmp_path / "room.ply"), "--json"])
        == 0
    )
    meshed = json.loads(capsys.readouterr().out)
    assert set(meshed["visible_ids"]) <= set(free["visible_ids"])
    # landmarks lie on the room's surfaces: few are hidden by the surface they lie on
    assert meshed["num_visible"] >= 0.8 * free["num_visible"]
    assert meshed["num_visible"] + meshed["num_occluded"] == free["num_visible"]
    # a wall right in front of the camera hides everything: exit status 1
    wall = trimesh.creation.box(extents=[50, 50, 0.01])
    wall.apply_transform(
        inverse(T) @ np.diag([1, 1, 1, 1.0]) @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.3], [0, 0, 0, 1.0]])
    )
    wall.export(tmp_path / "wall.obj")
    assert (
        main(["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--mesh", str(tmp_path / "wall.obj"), "--json"])
        == 1
    )
    cap = capsys.readouterr()
    assert json.loads(cap.out)["num_visible"] == 0 and "no landmark is visible" in cap.err


# -- CLI end to end and failure modes -----------------------------------------------------------------
def test_merge_cli_end_to_end(small_map, tmp_path, capsys):
    from favormap.cli import main

    m, path = small_map
    out = tmp_path / "m.h5"
    assert main(["merge", str(path), str(path), str(path), "-o", str(out), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["num_landmarks"] == m.num_landmarks and s["num_frames"] == 3 * m.num_frames
    check_written_map(out)
    assert main(["merge", str(path), str(path), "-o", str(out), "--no-dedup", "-q"]) == 0
    assert "merged" in capsys.readouterr().out
    d = check_written_map(out)
    assert d.num_landmarks == 2 * m.num_landmarks


def test_cli_bad_inputs_fail_with_one_line(small_map, tmp_path, capsys):
    from favormap.cli import main

    m, path = small_map
    out = str(tmp_path / "o.h5")
    (tmp_path / "bad_t.txt").write_text("1 0 0\n0 1 0\n")
    (tmp_path / "shear.txt").write_text("1 1 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    (tmp_path / "notamap.h5").write_text("hello")
    (tmp_path / "pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    c32 = write_variant(
        m,
        tmp_path / "c32.h5",
        channels=32,
        descriptors=m.descriptors[..., :32],
        mean_descriptor=m.mean_descriptor[:, :32],
    )
    cases = [
        (["query", str(tmp_path / "missing.h5"), "--pose", str(tmp_path / "pose.txt")], "not found"),
        (["query", str(tmp_path / "notamap.h5"), "--near", "0", "0", "0", "--knn", "3"], "not a favormap map"),
        (["query", str(path), "--pose", str(tmp_path / "missing_pose.txt")], "not found"),
        (["query", str(path), "--pose", str(tmp_path / "shear.txt")], "not a rotation"),
        (["query", str(path), "--near", "0", "0", "0"], "--radius"),
        (["query", str(path), "--pose", str(tmp_path / "pose.txt"), "--mesh", str(tmp_path / "pose.txt")], "mesh"),
        (["merge", str(path), str(tmp_path / "missing.h5"), "-o", out, "-q"], "not found"),
        (["merge", str(path), str(path), "-o", out, "--transform", str(tmp_path / "bad_t.txt"), "-q"], "bad_t.txt"),
        (["merge", str(path), str(path), "-o", out, "--transform", str(tmp_path / "shear.txt"), "-q"], "shear.txt"),
        (["merge", str(path), str(c32), "-o", out, "-q"], "different channels"),
        (["merge", str(path), "-o", out, "-q"], "at least two"),
        (["merge", str(path), str(path), "-o", str(tmp_path / "nodir" / "o.h5"), "-q"], "does not exist"),
        (["prune", str(path), "-o", out, "--min-quality", "1000", "-q"], "would remove all"),
        (["prune", str(path), "-o", out, "--max-landmarks", "0", "-q"], "max-landmarks"),
        (["export", str(tmp_path / "notamap.h5"), "-o", str(tmp_path / "x.ply")], "not a favormap map"),
    ]
    for argv, needle in cases:
        rc = main(argv)
        line = one_error_line(capsys)
        assert rc != 0 and needle in line, (argv, rc, line)
    assert not (tmp_path / "o.h5").exists()


# -- merged halves localize like the whole --------------------------------------------------------------
def test_merged_halves_localize_as_well_as_the_whole_map(small_sequence, small_map, tmp_path):
    localize = pytest.importorskip("favormap.localize")
    from conftest import small_build_config

    from favormap.build import build_map
    from favormap.geometry import perturb_pose, pose_error
    from favormap.ops.merge import merge_maps
    from favormap.synthetic import make_room, random_views_near, render

    _, whole = small_map
    n = len(small_sequence)
    halves = [small_sequence.subset(range(n // 2)), small_sequence.subset(range(n // 2, n))]
    paths = []
    for i, h in enumerate(halves):
        mh = build_map(h, small_build_config(max_landmarks=200, iterations=80))
        paths.append(write_map(mh, tmp_path / f"half{i}.h5"))
    merged = merge_maps(paths, tmp_path / "merged.h5").path
    check_written_map(merged)
    scene = make_room(0)
    cam = small_sequence.cameras[0]
    rng = np.random.default_rng(11)
    queries = []
    for i, h in enumerate(halves):
        views = random_views_near(
            [f.cam_from_world for f in h.frames], 3, seed=20 + i, max_trans=0.08, max_rot_deg=4.0, scene=scene
        )
        queries += [(render(scene, cam, T)[0], T, perturb_pose(T, 0.1, 5.0, rng)) for T in views]
    results = {}
    for name, p in (("whole", whole), ("merged", merged)):
        loc = localize.Localizer(p, localize.LocalizeConfig(iterations=3))
        res = [loc.localize(img, prior) for img, _, prior in queries]
        loc.close()
        errs = np.array(
            [pose_error(r.cam_from_world, T) if r.success else (np.inf, np.inf) for r, (_, T, _) in zip(res, queries)]
        )
        results[name] = (np.array([r.success for r in res]), errs)
    ok_w, err_w = results["whole"]
    ok_m, err_m = results["merged"]
    assert ok_m.sum() >= ok_w.sum() - 1, (ok_m, ok_w)
    for half in (slice(0, 3), slice(3, 6)):  # both halves' queries localize on the merged map
        assert ok_m[half].sum() >= 2, ok_m
        assert np.median(err_m[half, 0]) <= max(2 * np.median(err_w[half, 0]), 0.01), (err_m, err_w)
