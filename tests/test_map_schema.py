"""schemas/favormap-map.v1.json is a JSON Schema of a map's layout description: it validates what
``favormap validate --json`` prints for a real map and rejects broken descriptions."""

from __future__ import annotations

import copy
import importlib.util
import json
import shutil
import sys
from pathlib import Path

import h5py
import jsonschema
import numpy as np
import pytest

from favormap.cli import main
from favormap.mapfile import FORMAT_VERSION, POSE_CONVENTION, describe_layout, load_schema
from favormap.mapfile.validate import validate

REPO = Path(__file__).resolve().parents[1]
SCHEMA_PATH = REPO / "schemas" / f"favormap-map.v{FORMAT_VERSION}.json"


def _schema() -> dict:
    return json.loads(SCHEMA_PATH.read_text())


def _validator() -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(_schema(), format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER)


def _errors(instance) -> list[str]:
    return [e.message for e in _validator().iter_errors(instance)]


@pytest.fixture(scope="module")
def description(small_map):
    return describe_layout(small_map[1])


def test_the_schema_is_a_draft_2020_12_json_schema():
    s = _schema()
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema" and s["$id"].endswith(SCHEMA_PATH.name)
    jsonschema.Draft202012Validator.check_schema(s)
    # titles and descriptions on every entry (the doc tables are generated from them)
    for section in ("attributes", "datasets"):
        for name, e in s["properties"][section]["properties"].items():
            assert e["title"] == name and e["description"].strip(), name
    for name, e in s["properties"].items():
        assert e.get("title") and e.get("description"), name


def test_the_packaged_schema_is_the_top_level_one():
    packaged = REPO / "favormap" / "schemas" / SCHEMA_PATH.name
    assert packaged.read_bytes() == SCHEMA_PATH.read_bytes()


def test_favormaps_checks_agree_with_the_json_schema():
    """Each entry's x-favormap (what favormap.mapfile.schema checks) says what its JSON Schema says."""
    s = _schema()
    ds = s["properties"]["datasets"]
    required = set(ds["required"])
    for path, e in ds["properties"].items():
        x = e["x-favormap"]
        assert e["properties"]["dtype"]["enum"] == [x["dtype"]], path
        items = e["properties"]["shape"]["prefixItems"]
        assert len(items) == len(x["shape"]) == e["properties"]["shape"]["maxItems"], path
        for item, sym in zip(items, x["shape"]):
            assert item.get("const") == sym if isinstance(sym, int) else item["minimum"] == 0, path
        assert (path in required) == (not x.get("optional")), path
    at = s["properties"]["attributes"]
    assert set(at["required"]) == set(at["properties"])
    for name, e in at["properties"].items():
        x = e["x-favormap"]
        assert e["properties"]["type"]["const"] == x["type"], name
        assert e["properties"]["value"].get("const") == x.get("const"), name
        assert e["properties"]["value"].get("minimum") == x.get("min"), name
    assert load_schema()["datasets"]["landmarks/ids"]["dtype"] == "uint64"
    assert "favormap.mapfile.schema.MIGRATIONS" in s["$comment"]


def test_a_real_map_validates(small_map, description):
    _, path = small_map
    assert _errors(description) == []
    report = validate(path)
    assert report.valid and report.format_version == FORMAT_VERSION
    out = report.to_dict()
    assert out["valid"] is True and out["datasets"] == description["datasets"] and _errors(out) == []


def test_validate_json_prints_a_valid_description(small_map, capsys):
    _, path = small_map
    assert main(["validate", "--json", str(path)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["valid"] is True and out["format_version"] == FORMAT_VERSION and _errors(out) == []
    assert out["attributes"]["num_landmarks"]["value"] == out["num_landmarks"] > 0


def test_the_standalone_reader_describes_the_same(small_map, description):
    spec = importlib.util.spec_from_file_location("read_map_standalone", REPO / "tools" / "read_map_standalone.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    assert mod.describe(small_map[1]) == description


def test_string_types_and_pose_convention_are_as_documented(small_map, description):
    """Attributes: variable-length UTF-8; string datasets: fixed-length, HDF5 ASCII character set."""
    a, d = description["attributes"], description["datasets"]
    assert a["extractor"]["string"] == {"length": "variable", "encoding": "utf-8"}
    for p in ("frames/names", "cameras/models"):
        assert (
            d[p]["dtype"] == "str"
            and d[p]["string"]["encoding"] == "ascii"
            and isinstance(d[p]["string"]["length"], int)
        )
    assert a["pose_convention"]["value"] == POSE_CONVENTION
    assert _schema()["properties"]["attributes"]["properties"]["pose_convention"]["properties"]["value"]["const"] == (
        POSE_CONVENTION
    )
    for name in ("channels", "num_landmarks"):
        assert a[name]["dtype"] == "int64"


@pytest.mark.parametrize("instance", [{}, 42, [], "map", None])
def test_non_descriptions_are_rejected(instance):
    assert _errors(instance)


def test_a_missing_required_dataset_is_rejected(description):
    bad = copy.deepcopy(description)
    del bad["datasets"]["landmarks/voxel_size"]
    assert any("landmarks/voxel_size" in m for m in _errors(bad))
    # an optional dataset may be absent
    ok = copy.deepcopy(description)
    ok["datasets"].pop("tracks/patch", None)
    assert _errors(ok) == []


def test_a_wrong_dtype_shape_attribute_or_checksum_is_rejected(description):
    def mutated(fn):
        bad = copy.deepcopy(description)
        fn(bad)
        return _errors(bad)

    assert mutated(lambda b: b["datasets"]["landmarks/positions"].update(dtype="float32"))
    assert mutated(lambda b: b["datasets"]["voxels/density"].update(dtype="float16"))
    assert mutated(
        lambda b: b["datasets"]["landmarks/positions"].update(shape=[b["datasets"]["landmarks/ids"]["shape"][0], 4])
    )
    assert mutated(lambda b: b["datasets"]["frames/cam_from_world"].update(shape=[3, 4]))
    assert mutated(lambda b: b["datasets"]["tracks/xy"].update(fletcher32=False))
    assert mutated(lambda b: b["attributes"]["format"].update(value="other-map"))
    assert mutated(lambda b: b["attributes"]["grid_resolution"].update(value=1))
    assert mutated(lambda b: b["attributes"].pop("channels"))
    assert mutated(lambda b: b["groups"].remove("voxels"))


def test_a_file_with_a_wrong_dtype_is_rejected_by_both(small_map, tmp_path):
    """A real file rewritten with float32 positions: its description fails the schema and validate."""
    p = tmp_path / "bad.h5"
    shutil.copy(small_map[1], p)
    with h5py.File(p, "r+") as f:
        pos = f["landmarks/positions"][()]
        del f["landmarks/positions"]
        f.create_dataset("landmarks/positions", data=pos.astype(np.float32), chunks=True, fletcher32=True)
    assert any("float32" in m for m in _errors(describe_layout(p)))
    assert not validate(p).valid


def test_validate_json_reports_the_version_of_a_newer_file(small_map, tmp_path, capsys):
    p = tmp_path / "v2.h5"
    shutil.copy(small_map[1], p)
    with h5py.File(p, "r+") as f:
        f.attrs["format_version"] = FORMAT_VERSION + 1
    assert main(["validate", "--json", str(p)]) != 0
    out = json.loads(capsys.readouterr().out)
    assert (
        out["valid"] is False
        and out["format_version"] == FORMAT_VERSION + 1
        and "upgrade favormap" in out["problems"][0]
    )


def _load_tables_tool():
    spec = importlib.util.spec_from_file_location("gen_map_format_tables", REPO / "tools" / "gen_map_format_tables.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_docs_tables_are_the_generated_ones():
    tool = _load_tables_tool()
    doc = (REPO / "docs" / "map-format.md").read_text()
    assert tool.render(doc, _schema()) == doc
    for name, table in tool.tables(_schema()).items():
        assert f"<!-- generated: {name} -->\n{table}\n<!-- end generated -->" in doc
    # a changed description shows
    s = _schema()
    s["properties"]["datasets"]["properties"]["tracks/xy"]["description"] = "changed"
    assert tool.render(doc, s) != doc
    assert tool.main(["--check"]) == 0


def test_the_docs_camera_parameters_are_favormaps():
    from favormap.io.types import SUPPORTED_MODELS

    doc = (REPO / "docs" / "map-format.md").read_text()
    for model, names in SUPPORTED_MODELS.items():
        assert f"| `{model}` | {len(names)} | {', '.join(names)} |" in doc, model


def test_documented_units_and_norms_hold_on_a_built_map(small_map):
    """depth_range: distances landmark - camera centre (not z-depths); mean_descriptor unit length,
    grid nodes not; voxel_size = box_factor * min distance / ((fx + fy) / 2) of the working cameras."""
    from favormap.geometry import camera_centers
    from favormap.io.images import working_camera

    m, path = small_map
    with h5py.File(path, "r") as f:
        prov = json.loads(f.attrs["provenance"])
        max_side = int(f.attrs["max_side"])
    centres = camera_centers(m.cam_from_world)[m.track_frame]
    dist = np.linalg.norm(m.positions[m.track_landmark] - centres, axis=1)
    lo, hi = np.full(len(m.positions), np.inf), np.zeros(len(m.positions))
    np.minimum.at(lo, m.track_landmark, dist)
    np.maximum.at(hi, m.track_landmark, dist)
    np.testing.assert_allclose(m.depth_range, np.stack([lo, hi], 1), rtol=1e-5)
    cam_of = dict(zip(range(len(m.frame_camera_ids)), m.frame_camera_ids))
    focal = np.array(
        [
            (lambda K: 0.5 * (K[0, 0] + K[1, 1]))(working_camera(m.cameras[int(cam_of[int(i)])], max_side).K)
            for i in m.track_frame
        ]
    )
    size = np.full(len(m.positions), np.inf)
    np.minimum.at(size, m.track_landmark, prov["config"]["voxel"]["box_factor"] * dist / focal)
    np.testing.assert_allclose(m.voxel_size, size, rtol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(m.mean_descriptor, axis=1), 1, atol=2e-3)
    nodes = np.linalg.norm(m.descriptors.reshape(-1, m.descriptors.shape[-1]), axis=1)
    assert np.abs(nodes - 1).max() > 0.05
