"""The map format contract: schema, integrity (Fletcher-32), versions, validation, no code from data.

Maps here are written from random MapData (no build pipeline), so the file is fast."""

from __future__ import annotations

import ast
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from favormap.errors import FavormapError, MapFormatError
from favormap.geometry import rotation_about
from favormap.io import Camera
from favormap.mapfile import (
    FORMAT_VERSION,
    Map,
    MapData,
    check_file,
    load_schema,
    write_map,
)
from favormap.mapfile import schema as schema_mod
from favormap.mapfile.validate import validate

ROOT = Path(__file__).resolve().parents[1]


def random_map(seed: int = 0, L: int = 20, C: int = 8, R: int = 3, M: int = 5, obs_per_landmark: int = 3) -> MapData:
    """A small, valid MapData with random content of the right shapes."""
    rng = np.random.default_rng(seed)
    ids = (rng.permutation(10 * L + 1)[:L] * 7919 + 1 + rng.integers(0, 2**40)).astype(np.uint64)  # unique, non-zero
    vd = rng.normal(size=(L, 3))
    vd /= np.linalg.norm(vd, axis=1, keepdims=True)
    dmin = rng.uniform(0.5, 2.0, L)
    T = np.tile(np.eye(4), (M, 1, 1))
    for i in range(M):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        T[i, :3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        T[i, :3, 3] = rng.normal(size=3)
    k = min(obs_per_landmark, M)
    tl = np.repeat(np.arange(L), k).astype(np.int32)
    tf = (
        np.concatenate([rng.choice(M, size=k, replace=False) for _ in range(L)]).astype(np.int32)
        if L
        else np.zeros(0, np.int32)
    )
    cams = {
        0: Camera("PINHOLE", 320, 240, np.array([300.0, 300.0, 160.0, 120.0])),
        3: Camera("OPENCV", 640, 480, np.array([500.0, 500.0, 320.0, 240.0, 0.01, -0.02, 0.0, 0.0]), 70.0),
    }
    return MapData(
        extractor="sift",
        channels=C,
        grid_resolution=R,
        patch_size=7,
        render_samples=12,
        max_side=0,
        ids=ids,
        positions=rng.normal(size=(L, 3)),
        voxel_size=rng.uniform(0.01, 0.1, L).astype(np.float32),
        track_length=np.full(L, k, np.int32),
        reproj_error=rng.uniform(0, 2, L).astype(np.float32),
        quality=rng.uniform(20, 40, L).astype(np.float32),
        cosine=rng.uniform(0.5, 1, L).astype(np.float32),
        view_dir=vd.astype(np.float32),
        view_angle=rng.uniform(0, 30, L).astype(np.float32),
        depth_range=np.stack([dmin, dmin + rng.uniform(0, 1, L)], 1).astype(np.float32),
        mean_descriptor=rng.normal(size=(L, C)).astype(np.float32),
        descriptors=rng.normal(size=(L, R, R, R, C)).astype(np.float32),
        density=rng.normal(size=(L, R, R, R)).astype(np.float32),
        cameras=cams,
        frame_names=[f"images/{i:06d}.png" for i in range(M)],
        frame_camera_ids=np.array([0, 3] * (M // 2) + [0] * (M % 2), np.int32),
        cam_from_world=T,
        track_landmark=tl,
        track_frame=tf,
        track_xy=rng.uniform(0, 300, (len(tl), 2)).astype(np.float32),
        track_patch=rng.integers(0, 256, (len(tl), 5, 5), dtype=np.uint8),
        provenance={"source": "random", "seed": seed, "stats": {"landmarks": L}},
        cam_from_rig=np.block([[rotation_about(rng.normal(size=3), 0.02), np.zeros((3, 1))], [np.zeros((1, 3)), 1]]),
    )


@pytest.fixture(scope="module")
def rmap(tmp_path_factory):
    m = random_map(0)
    path = tmp_path_factory.mktemp("rmap") / "r.h5"
    write_map(m, path)
    return m, path


def copy(path: Path, tmp_path: Path, name="c.h5") -> Path:
    out = tmp_path / name
    shutil.copyfile(path, out)
    return out


def read_all(path) -> None:
    with Map.open(path) as m:
        m.voxels(np.arange(len(m)))
        m.mean_descriptors(np.arange(len(m)))
        m.tracks()
        m.info()


# -- schema and roundtrip ---------------------------------------------------------------------------
def test_schema_is_consistent_with_the_code():
    s = load_schema()
    assert s["format"] == "favormap-map" and s["version"] == FORMAT_VERSION
    assert {"compatibility", "attributes", "datasets"} <= set(s)
    assert "favormap.mapfile.schema.MIGRATIONS" in s["$comment"]  # the migrations live in Python
    from favormap.io.types import SUPPORTED_MODELS

    assert s["datasets"]["cameras/models"]["values"]["enum"] == list(SUPPORTED_MODELS)
    # every per-landmark dataset of this version is a field of MapData (none ride in MapData.extra)
    assert set(MapData.landmark_names()) <= set(MapData.__dataclass_fields__)
    assert set(s["datasets"]) == set(
        f"landmarks/{k}" for k in MapData.landmark_names() if k not in ("descriptors", "density")
    ) | {
        "voxels/descriptors",
        "voxels/density",
        "cameras/ids",
        "cameras/models",
        "cameras/sizes",
        "cameras/params",
        "cameras/working_fov",
        "frames/names",
        "frames/camera_ids",
        "frames/cam_from_world",
        "frames/cam_from_rig",
        "tracks/landmark_index",
        "tracks/frame_index",
        "tracks/xy",
        "tracks/patch",
    }
    # the datasets a map may lack: the observation patches of `build --align-patches`, the working field of
    # view of cameras that all follow the default rule, and the camera's rotation of maps built without one
    assert {p for p, d in s["datasets"].items() if d.get("optional")} == {
        "tracks/patch",
        "cameras/working_fov",
        "frames/cam_from_rig",
    }
    known = {
        "finite",
        "not_nan",
        "min",
        "max",
        "exclusive_min",
        "unique",
        "nonzero",
        "range",
        "in",
        "enum",
        "unit_norm",
        "rigid",
        "ordered",
        "consistent_with",
    }
    for p, spec in s["datasets"].items():
        assert set(spec.get("values", {})) <= known, p
    assert set(schema_mod.MIGRATIONS) == set(range(1, FORMAT_VERSION))  # one step per older version


def test_roundtrip_and_every_dataset_has_fletcher32(rmap):
    m, path = rmap
    with h5py.File(path, "r") as f:
        assert check_file(f) == []
        for p in load_schema()["datasets"]:
            assert f[p].fletcher32 and f[p].chunks is not None, p
        assert f.attrs["format"] == "favormap-map"
    with Map.open(path) as mm:
        np.testing.assert_array_equal(mm.ids, m.ids)
        np.testing.assert_allclose(mm.positions, m.positions)
        d, s = mm.voxels([5, 2, 5])
        np.testing.assert_allclose(d[1], m.descriptors[2].reshape(27, -1), atol=4e-3)
        np.testing.assert_allclose(s[0], m.density[5].reshape(-1))
        np.testing.assert_allclose(mm.mean_descriptors([3, 1, 3]), m.mean_descriptor[[3, 1, 3]], atol=4e-3)
        assert mm.cameras[3].model == "OPENCV" and mm.frame_names == m.frame_names
        assert mm.cameras[3].working_fov == 70.0 and mm.cameras[0].working_fov is None
        tl, tf, xy = mm.tracks()
        np.testing.assert_array_equal(tl, m.track_landmark)
        back = mm.load()
        assert back.num_landmarks == m.num_landmarks and back.provenance == m.provenance
    r = validate(path)
    assert r.valid and r.problems == [] and r.warnings == [] and r.datasets_read == len(load_schema()["datasets"])


def test_empty_map_roundtrips(tmp_path):
    m = random_map(1, L=0, M=0)
    m.cameras = {}
    m.frame_camera_ids = np.zeros(0, np.int32)
    write_map(m, tmp_path / "e.h5")
    with Map.open(tmp_path / "e.h5") as mm:
        assert len(mm) == 0 and mm.voxels([])[0].shape == (0, 27, 8)
    assert validate(tmp_path / "e.h5").valid


def test_writer_refuses_invalid_maps_before_creating_a_file(tmp_path):
    out = tmp_path / "bad.h5"
    cases = {
        "duplicated": lambda m: m.ids.__setitem__(1, m.ids[0]),
        "zero": lambda m: m.ids.__setitem__(0, 0),
        "not finite": lambda m: m.positions.__setitem__((2, 1), np.nan),
        "not above 0": lambda m: m.voxel_size.__setitem__(0, 0.0),
        "index out of range": lambda m: m.track_landmark.__setitem__(0, 99),
        "not unit length": lambda m: m.view_dir.__setitem__(0, [1, 1, 0]),
        "rigid": lambda m: m.cam_from_world.__setitem__((0, 0, 0), 3.0),
        "not in 'cameras/ids'": lambda m: m.frame_camera_ids.__setitem__(0, 7),
        "along 'L'": lambda m: setattr(m, "quality", m.quality[:-1]),
        "not JSON serialisable": lambda m: m.provenance.__setitem__("x", object()),
        # the float16 datasets are checked in their own dtype, the compared ones in float64
        "'voxels/descriptors': 1 value not finite": lambda m: m.descriptors.__setitem__((1, 0, 1, 2, 3), np.inf),
        "'landmarks/mean_descriptor': 1 value not finite": lambda m: m.mean_descriptor.__setitem__((0, 2), np.nan),
        "above 180": lambda m: m.view_angle.__setitem__(0, 180.5),
        "'landmarks/reproj_error': 1 value below 0": lambda m: m.reproj_error.__setitem__(1, -0.25),
        "rows not in increasing order": lambda m: m.depth_range.__setitem__(0, [2.0, 1.0]),
    }
    for expect, corrupt in cases.items():
        m = random_map(2)
        corrupt(m)
        with pytest.raises(MapFormatError, match=expect):
            write_map(m, out)
        assert not out.exists() and not list(tmp_path.iterdir()), expect


# -- integrity ---------------------------------------------------------------------------------------
def _chunk_offset(path, dataset, row):
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        info = ds.id.get_chunk_info_by_coord((row,) + (0,) * (ds.ndim - 1))
        return info.byte_offset, info.size


def _flip(path, offset, n=1):
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = bytearray(fh.read(n))
        fh.seek(offset)
        fh.write(bytes(x ^ 0xFF for x in b))


@pytest.mark.parametrize("dataset", ["voxels/descriptors", "voxels/density"])
def test_flipped_byte_in_voxel_data_is_detected(rmap, tmp_path, dataset):
    _, path = rmap
    p = copy(path, tmp_path)
    off, size = _chunk_offset(p, dataset, 7)
    _flip(p, off + size // 2)
    with Map.open(p) as m:  # metadata is intact: opening works, the damaged landmark does not
        m.voxels([0, 1, 2])
        with pytest.raises(MapFormatError, match="voxel data is corrupted"):
            m.voxels([6, 7])
        with pytest.raises(MapFormatError, match="voxel data is corrupted"):
            m.load()
    r = validate(p)
    assert not r.valid
    assert len(r.problems) == 1 and dataset in r.problems[0] and "row(s) 7 " in r.problems[0], r.problems


def test_flipped_byte_in_landmark_metadata_fails_at_open(rmap, tmp_path):
    _, path = rmap
    p = copy(path, tmp_path)
    off, size = _chunk_offset(p, "landmarks/positions", 0)
    _flip(p, off + 3)
    with pytest.raises(MapFormatError, match="positions"):
        Map.open(p)
    assert any("positions" in q and "checksum" in q for q in validate(p).problems)


@pytest.mark.parametrize("keep", [0, 7, 100, 2048, 0.5, 0.99])
def test_truncated_file_gives_one_clear_error(rmap, tmp_path, keep):
    _, path = rmap
    data = path.read_bytes()
    n = int(len(data) * keep) if isinstance(keep, float) else keep
    p = tmp_path / "t.h5"
    p.write_bytes(data[:n])
    with pytest.raises(MapFormatError) as e:
        Map.open(p)
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg
    assert any(w in msg for w in ("truncated", "not a favormap map", "corrupted")), msg
    r = validate(p)
    assert not r.valid and r.problems


def test_foreign_files_are_refused(tmp_path):
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["data"] = np.arange(10)
        f.attrs["format"] = "something-else"
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    empty = tmp_path / "empty.h5"
    empty.write_bytes(b"")
    for p, expect in (
        (foreign, "not a favormap map"),
        (text, "not a favormap map"),
        (empty, "not a favormap map"),
        (tmp_path / "missing.h5", "not found"),
        (tmp_path, "directory"),
    ):
        with pytest.raises(MapFormatError, match=expect):
            Map.open(p)
        r = validate(p)
        assert not r.valid and r.problems, p
    assert len(validate(foreign).problems) == 1  # not a list of every missing dataset


def test_validate_reports_every_problem(rmap, tmp_path):
    _, path = rmap
    p = copy(path, tmp_path)
    with h5py.File(p, "r+") as f:
        del f["landmarks/cosine"]
        del f.attrs["created"]
        f.attrs["channels"] = "eight"
        ds = f["landmarks/ids"]
        ids = ds[()]
        ids[3] = ids[4]
        ds[...] = ids
        tl = f["tracks/landmark_index"]
        a = tl[()]
        a[0] = 1000
        tl[...] = a
        f.create_dataset("frames/camera_ids_new", data=np.zeros(3))
        del f["frames/cam_from_world"]
        f.create_dataset("frames/cam_from_world", data=np.zeros((5, 4, 4)))  # no checksum, not rigid
    r = validate(p)
    text = "\n".join(r.problems)
    for expect in (
        "missing dataset 'landmarks/cosine'",
        "missing root attribute 'created'",
        "'channels' should be an integer",
        "'landmarks/ids': 1 duplicated",
        "'tracks/landmark_index': 1 value outside [0, 20)",
        "'frames/cam_from_world' has no Fletcher-32",
        "'frames/cam_from_world': 5 values not a rigid",
    ):
        assert expect in text, (expect, text)
    assert any("frames/camera_ids_new" in w for w in r.warnings)
    with pytest.raises(MapFormatError, match="not a valid favormap map"):
        Map.open(p)


def test_value_problems_are_refused_at_open(rmap, tmp_path):
    _, path = rmap
    for dataset, row, value, expect in (
        ("landmarks/positions", (1, 0), np.inf, "not finite"),
        ("landmarks/voxel_size", 2, -1.0, "not above 0"),
        ("landmarks/ids", 0, 0, "zero"),
        ("frames/camera_ids", 1, 42, "not in"),
    ):
        p = copy(path, tmp_path)
        with h5py.File(p, "r+") as f:
            a = f[dataset][()]
            a[row] = value
            f[dataset][...] = a
        with pytest.raises(MapFormatError, match=expect):
            Map.open(p)
        assert any(expect in q for q in validate(p).problems)
    p = copy(path, tmp_path)
    with h5py.File(p, "r+") as f:
        a = f["tracks/frame_index"][()]
        a[2] = -1
        f["tracks/frame_index"][...] = a
    with Map.open(p) as m:  # tracks are read lazily: checked when read
        with pytest.raises(MapFormatError, match="out of range"):
            m.tracks()


# -- versions ---------------------------------------------------------------------------------------
def test_newer_format_version_is_refused_with_a_clear_message(rmap, tmp_path):
    _, path = rmap
    p = copy(path, tmp_path)
    with h5py.File(p, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(MapFormatError) as e:
        Map.open(p)
    msg = str(e.value)
    assert (
        f"has map format version {FORMAT_VERSION + 1}, this favormap reads up to {FORMAT_VERSION}: upgrade favormap"
        in msg
    )
    r = validate(p)
    assert r.problems == [msg]  # one problem: a future layout is not checked against this schema
    with h5py.File(p, "r+") as f:
        f.attrs["format_version"] = 0
    with pytest.raises(MapFormatError, match="invalid format_version 0"):
        Map.open(p)


def test_older_versions_are_migrated_in_memory(rmap, tmp_path, monkeypatch):
    """Simulate favormap with format version 2, where v2 renamed ``landmarks/quality`` to
    ``landmarks/psnr`` and added the attribute ``units``: a v1 file still opens, read through
    schema v1 and MIGRATIONS[1], without being rewritten."""
    _, path = rmap
    v1 = load_schema(1)
    v2 = json.loads(json.dumps(v1))
    v2["version"] = 2
    v2["datasets"]["landmarks/psnr"] = v2["datasets"].pop("landmarks/quality")
    v2["attributes"]["units"] = {"type": "str"}
    sdir = tmp_path / "schemas"
    sdir.mkdir()
    (sdir / "favormap-map.v1.json").write_text(json.dumps(v1))
    (sdir / "favormap-map.v2.json").write_text(json.dumps(v2))

    def migrate_1_to_2(view):
        view.datasets["landmarks/psnr"] = view.datasets.pop("landmarks/quality")
        view.attrs["units"] = "unknown"

    monkeypatch.setattr(schema_mod, "_schema_dir", lambda: sdir)
    monkeypatch.setattr(schema_mod, "FORMAT_VERSION", 2)
    monkeypatch.setitem(schema_mod.MIGRATIONS, 1, migrate_1_to_2)
    schema_mod.load_schema.cache_clear()
    try:
        p = copy(path, tmp_path)
        before = p.read_bytes()
        with h5py.File(p, "r") as f:
            assert schema_mod.check_file(f, 2) == []
            view = schema_mod.open_view(f, p, 2)
            assert view.version == 2 and "landmarks/psnr" in view.datasets and view.attrs["units"] == "unknown"
        assert p.read_bytes() == before
        # without the migration the v2 reader cannot read v1
        monkeypatch.delitem(schema_mod.MIGRATIONS, 1)
        with h5py.File(p, "r") as f:
            assert "no migration from map format version 1 to 2" in schema_mod.check_file(f, 2)[0]
    finally:
        schema_mod.load_schema.cache_clear()


def test_a_landmark_field_added_to_the_schema_is_carried_everywhere(tmp_path, monkeypatch):
    """The schema is the one list of landmark fields: a copy of it with one more per-landmark
    dataset is read, written, selected, merged and pruned without touching the code."""
    from favormap.ops.merge import MergeConfig, merge_maps
    from favormap.ops.prune import prune_map

    v1 = json.loads(json.dumps(load_schema(1)))
    v1["datasets"]["landmarks/sharpness"] = {
        "dtype": "float32",
        "shape": ["L"],
        "values": {"finite": True, "min": 0},
        "description": "a field added by the test",
    }
    sdir = tmp_path / "schemas"
    sdir.mkdir()
    (sdir / "favormap-map.v1.json").write_text(json.dumps(v1))
    monkeypatch.setattr(schema_mod, "_schema_dir", lambda: sdir)
    schema_mod.load_schema.cache_clear()
    try:
        m = random_map(3, L=30)
        sharp = np.random.default_rng(3).uniform(0, 5, m.num_landmarks).astype(np.float32)
        with pytest.raises(MapFormatError, match="sharpness"):  # a map without the new field cannot be written
            write_map(m, tmp_path / "missing.h5")
        m.extra["sharpness"] = sharp
        a = write_map(m, tmp_path / "a.h5")
        with h5py.File(a, "r") as f:
            assert "landmarks/sharpness" in f and check_file(f) == []
        with Map.open(a) as mp:  # read: in memory at open, and in load()
            np.testing.assert_array_equal(mp.sharpness, sharp)
            np.testing.assert_array_equal(mp.load().sharpness, sharp)
        sel = m.select_landmarks(np.array([4, 1, 7]))
        np.testing.assert_array_equal(sel.sharpness, sharp[[4, 1, 7]])
        # merge: the same map twice keeps every landmark once, with its value
        merged = merge_maps([a, a], tmp_path / "merged.h5").path
        with Map.open(merged) as mp:
            assert len(mp) == m.num_landmarks
            order = np.argsort(m.ids)
            np.testing.assert_array_equal(mp.sharpness[np.argsort(mp.ids)], sharp[order])
        # merge without dedup (every landmark twice) and prune by quality
        both = merge_maps([a, a], tmp_path / "both.h5", MergeConfig(dedup=False)).path
        with Map.open(both) as mp:
            np.testing.assert_array_equal(mp.sharpness, np.concatenate([sharp, sharp]))
        keep = m.quality >= np.median(m.quality)
        pruned = prune_map(a, tmp_path / "pruned.h5", min_quality=float(np.median(m.quality))).path
        with Map.open(pruned) as mp:
            np.testing.assert_array_equal(mp.ids, m.ids[keep])
            np.testing.assert_array_equal(mp.sharpness, sharp[keep])
    finally:
        schema_mod.load_schema.cache_clear()


# -- locking ----------------------------------------------------------------------------------------
def test_reader_does_not_lock_and_coexists_with_atomic_replace(rmap, tmp_path):
    """Readers open with locking=False: an open reader keeps reading its (old) file while a writer
    replaces the path, and a new reader sees the complete new map."""
    m0, path = rmap
    p = copy(path, tmp_path)
    with Map.open(p) as old:
        m1 = random_map(5)
        write_map(m1, p)
        with Map.open(p) as new:
            np.testing.assert_array_equal(new.ids, m1.ids)
        d, _ = old.voxels(np.arange(len(old)))
        np.testing.assert_allclose(d, m0.descriptors.reshape(m0.num_landmarks, 27, -1), atol=4e-3)
        np.testing.assert_array_equal(old.ids, m0.ids)


# -- no code execution from data ----------------------------------------------------------------------
def _calls(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            base = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else ""
            yield node, base, name


def test_no_code_execution_from_data():
    """No pickle/marshal/eval of data anywhere in the package; torch.load only with weights_only=True;
    np.load only with allow_pickle=False; yaml only safe_load."""
    files = sorted((ROOT / "favormap").rglob("*.py"))
    assert len(files) > 10
    bad = []
    for path in files:
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = [a.name for a in node.names] + (
                    [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
                )
                for mod in mods:
                    if mod.split(".")[0] in ("pickle", "cPickle", "dill", "marshal", "shelve", "cloudpickle", "joblib"):
                        bad.append(f"{path}:{node.lineno} imports {mod}")
        for node, base, name in _calls(tree):
            kw = {k.arg: k.value for k in node.keywords}
            where = f"{path.relative_to(ROOT)}:{node.lineno}"
            bare = isinstance(node.func, ast.Name) or base == "builtins"
            if name in ("eval", "exec", "compile", "__import__") and bare:
                bad.append(f"{where} calls {name}()")
            if base == "torch" and name == "load":
                v = kw.get("weights_only")
                if not (isinstance(v, ast.Constant) and v.value is True):
                    bad.append(f"{where} torch.load without weights_only=True")
            if base in ("np", "numpy") and name == "load":
                v = kw.get("allow_pickle")
                if v is not None and not (isinstance(v, ast.Constant) and v.value is False):
                    bad.append(f"{where} np.load with allow_pickle")
            if base == "yaml" and name in ("load", "unsafe_load", "full_load"):
                bad.append(f"{where} yaml.{name}")
            if name == "read_pickle":
                bad.append(f"{where} read_pickle")
    assert not bad, "\n".join(bad)


def test_provenance_is_json(rmap):
    _, path = rmap
    with h5py.File(path, "r") as f:
        prov = f.attrs["provenance"]
    assert isinstance(prov, str) and isinstance(json.loads(prov), dict)


def test_errors_are_favormap_errors():
    assert issubclass(MapFormatError, FavormapError)


def test_docs_match_the_schema():
    doc = (ROOT / "docs" / "map-format.md").read_text()
    s = load_schema()
    for name, spec in s["attributes"].items():
        assert f"| `{name}` | {spec['type']} |" in doc, name
    for path, spec in s["datasets"].items():
        assert f"| `{path}` | {spec['dtype']} | ({', '.join(map(str, spec['shape']))}) |" in doc, path
    assert f"version {FORMAT_VERSION}" in doc and "upgrade favormap" in doc and ".partial" in doc
