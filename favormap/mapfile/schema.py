"""The map layout contract: loads ``schemas/favormap-map.v<N>.json`` and checks files against it."""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

FORMAT = "favormap-map"
FORMAT_VERSION = 1


def _schema_dir() -> Path:
    # installed package data first, then the source checkout's top-level schemas/
    here = Path(__file__).resolve().parents[2] / "schemas"
    pkg = resources.files("favormap").joinpath("schemas")
    return Path(str(pkg)) if pkg.is_dir() else here


@lru_cache(maxsize=None)
def load_schema(version: int = FORMAT_VERSION) -> dict:
    return json.loads((_schema_dir() / f"favormap-map.v{version}.json").read_text())


def numpy_dtype(name: str):
    import h5py

    return h5py.string_dtype() if name == "str" else np.dtype(name)


def check_file(f, version: int = FORMAT_VERSION) -> list[str]:
    """All problems of an open h5py.File against the schema (empty list: valid)."""
    import h5py

    schema = load_schema(version)
    problems: list[str] = []
    attrs = f.attrs
    dims: dict[str, int] = {}
    for name, spec in schema["attributes"].items():
        if name not in attrs:
            problems.append(f"missing root attribute {name!r}")
            continue
        v = attrs[name]
        if isinstance(v, bytes):
            v = v.decode()
        if spec["type"] == "str" and not isinstance(v, str):
            problems.append(f"attribute {name!r} should be a string")
        elif spec["type"] == "int":
            if not isinstance(v, (int, np.integer)):
                problems.append(f"attribute {name!r} should be an integer")
                continue
            if v < spec.get("min", -np.inf):
                problems.append(f"attribute {name!r} = {v} is below {spec['min']}")
        if "const" in spec and v != spec["const"]:
            problems.append(f"attribute {name!r} is {v!r}, expected {spec['const']!r}")
    for sym, attr in (("C", "channels"), ("R", "grid_resolution"), ("L", "num_landmarks"), ("M", "num_frames")):
        if attr in attrs and isinstance(attrs[attr], (int, np.integer)):
            dims[sym] = int(attrs[attr])
    for path, spec in schema["datasets"].items():
        obj = f.get(path)
        if obj is None:
            problems.append(f"missing dataset {path!r}")
            continue
        if not isinstance(obj, h5py.Dataset):
            problems.append(f"{path!r} is not a dataset")
            continue
        want = spec["dtype"]
        if want == "str":
            if h5py.check_string_dtype(obj.dtype) is None:
                problems.append(f"{path!r} has dtype {obj.dtype}, expected strings")
        elif obj.dtype != np.dtype(want):
            problems.append(f"{path!r} has dtype {obj.dtype}, expected {want}")
        shape = spec["shape"]
        if len(obj.shape) != len(shape):
            problems.append(f"{path!r} has shape {obj.shape}, expected {tuple(shape)}")
            continue
        for n, s in zip(obj.shape, shape):
            if isinstance(s, int):
                if n != s:
                    problems.append(f"{path!r} has shape {obj.shape}, expected {tuple(shape)}")
                    break
            elif dims.setdefault(s, n) != n:
                problems.append(f"{path!r} has {n} along {s!r} but the map has {dims[s]}")
                break
        if obj.chunks is None or not obj.fletcher32:
            problems.append(f"{path!r} has no Fletcher-32 checksum")
    return problems
