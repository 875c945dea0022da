"""The map layout contract: loads ``schemas/favormap-map.v<N>.json`` and checks maps against it.

Three levels of checks, all driven by the schema (the single source of truth):

* :func:`check_header` - the magic ``format`` attribute and ``format_version`` (newer: refused);
* :func:`check_structure` - attributes (types, constants, minima, JSON), datasets (presence,
  dtype, shape, shared dimensions, chunking + Fletcher-32);
* :func:`check_values` - the ``values`` constraints of each dataset (finite numbers, unique
  non-zero ids, index ranges, unit vectors, rigid poses, ...), on arrays already in memory.

Compatibility: a reader of version ``FORMAT_VERSION`` reads every version ``<=`` it. A file of
version V is viewed through schema V (:class:`MapView`) and upgraded in memory by ``MIGRATIONS[V]``,
``MIGRATIONS[V + 1]``, ... up to ``FORMAT_VERSION``; newer files are refused with a clear message.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from datetime import datetime
from functools import cache
from pathlib import Path

import numpy as np

from ..errors import MapFormatError, first_line
from .value_checks import bound_problems, count_values, membership_problems, nonfinite_problems, row_problems

FORMAT = "favormap-map"
FORMAT_VERSION = 1

# the root attribute pose_convention of every map (the schema's const): how frames/cam_from_world
# and tracks/xy are to be read
POSE_CONVENTION = (
    "cam_from_world 4x4; OpenCV camera axes (x right, y down, z forward); "
    "pixel centre of the top-left pixel at (0.5, 0.5)"
)

# MIGRATIONS[V](view) upgrades a MapView of version V to version V + 1 in memory: rename or derive
# datasets/attributes (view.datasets values may become numpy arrays), then set view.version = V + 1.
# The migrations live here only (the schemas and docs/map-format.md point to this table); keep every
# old schemas/favormap-map.v<V>.json and say in each function's docstring what it changes.
MIGRATIONS: dict[int, Callable[[MapView], None]] = {}

# the dimension symbols that root attributes fix (the others, K and O, come from the datasets)
ATTR_DIMS = (("C", "channels"), ("R", "grid_resolution"), ("L", "num_landmarks"), ("M", "num_frames"))


def _schema_dir() -> Path:
    """favormap/schemas: package data in a wheel or ``pip install --target``; in a source checkout a
    link to the top-level schemas/ (the source of the files)."""
    return Path(__file__).resolve().parents[1] / "schemas"


@cache
def load_schema(version: int = FORMAT_VERSION) -> dict:
    """The schema of format ``version``: the JSON Schema file's content plus favormap's reading of
    it (:func:`layout_spec`): ``format``, ``version``, ``compatibility``, ``attributes`` and
    ``datasets`` (name -> the entry's ``x-favormap`` with its ``description``)."""
    path = _schema_dir() / f"favormap-map.v{int(version)}.json"
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise MapFormatError(
            f"no schema for map format version {version} ({path} is missing; broken installation?)"
        ) from None
    return raw if "datasets" in raw else {**raw, **layout_spec(raw)}


def layout_spec(json_schema: dict) -> dict:
    """favormap's checks from a JSON Schema of a layout description: each attribute's and dataset's
    ``x-favormap`` entry with its ``description``, in the schema's order."""
    props = json_schema["properties"]

    def entries(section: str) -> dict:
        return {
            name: {**e["x-favormap"], "description": e["description"]}
            for name, e in props[section]["properties"].items()
        }

    root = json_schema["x-favormap"]
    return {
        "format": root["format"],
        "version": root["version"],
        "compatibility": root["compatibility"],
        "attributes": entries("attributes"),
        "datasets": entries("datasets"),
    }


def numpy_dtype(name: str):
    import h5py

    return h5py.string_dtype() if name == "str" else np.dtype(name)


# -- header -----------------------------------------------------------------------------------------
def _attr(attrs, name):
    v = attrs.get(name) if hasattr(attrs, "get") else None
    if isinstance(v, bytes):
        try:
            v = v.decode()
        except UnicodeDecodeError:
            pass
    if isinstance(v, np.ndarray) and v.shape == ():
        v = v[()]
    return v


def check_header(attrs, path="map") -> int:
    """The format version of a file with root attributes ``attrs``; raises MapFormatError for a
    foreign file (no magic), an invalid version, or a version newer than this favormap reads."""
    fmt = _attr(attrs, "format")
    if fmt != FORMAT:
        if fmt is None:
            raise MapFormatError(
                f"{path} is not a favormap map (HDF5 file without format={FORMAT!r}; foreign or incompletely written)"
            )
        raise MapFormatError(f"{path} is not a favormap map (format attribute is {fmt!r}, expected {FORMAT!r})")
    ver = _attr(attrs, "format_version")
    if isinstance(ver, (bool, np.bool_)) or not isinstance(ver, (int, np.integer)):
        raise MapFormatError(f"{path}: missing or invalid format_version ({ver!r})")
    ver = int(ver)
    if ver > FORMAT_VERSION:
        raise MapFormatError(
            f"{path} has map format version {ver}, this favormap reads up to {FORMAT_VERSION}: upgrade favormap"
        )
    if ver < 1:
        raise MapFormatError(f"{path}: invalid format_version {ver}")
    return ver


# -- a map's content, version independent ----------------------------------------------------------
class MapView:
    """The attributes and datasets of a map as one schema version sees them. ``datasets`` maps
    schema paths to h5py datasets (read lazily) or, after a migration, numpy arrays; None when
    missing, or a string describing why the path is not a usable dataset."""

    def __init__(self, attrs: dict, datasets: dict, version: int):
        self.attrs = attrs
        self.datasets = datasets
        self.version = version
        self.extra: list[str] = []  # datasets in the file that the schema does not know

    @classmethod
    def from_file(cls, f, version: int) -> MapView:
        import h5py

        attrs = {}
        for k in f.attrs.keys():
            attrs[k] = _attr(f.attrs, k)
        datasets = {}
        for p in load_schema(version)["datasets"]:
            try:
                obj = f.get(p)
            except Exception as e:  # noqa: BLE001 - h5py raises many types on broken links/headers
                datasets[p] = f"cannot be opened ({first_line(e)})"
                continue
            if obj is None and _link_exists(f, p):
                obj = "cannot be opened (damaged object header)"
            elif obj is not None and not isinstance(obj, h5py.Dataset):
                obj = f"is a {type(obj).__name__.lower()}, not a dataset"
            datasets[p] = obj
        view = cls(attrs, datasets, version)
        known = set(load_schema(version)["datasets"])
        groups = {p.split("/")[0] for p in known}
        for g in sorted(set(f.keys())):
            obj = f.get(g)
            if g not in groups:
                view.extra.append(g)
            elif isinstance(obj, h5py.Group):
                view.extra += [f"{g}/{k}" for k in obj.keys() if f"{g}/{k}" not in known]
        return view

    def upgrade(self, to: int | None = None) -> MapView:
        """Apply the migrations from ``self.version`` up to ``to`` (default: FORMAT_VERSION)."""
        to = FORMAT_VERSION if to is None else to
        while self.version < to:
            step = MIGRATIONS.get(self.version)
            if step is None:
                raise MapFormatError(
                    f"no migration from map format version {self.version} to {self.version + 1} (broken installation?)"
                )
            v = self.version
            step(self)
            self.version = v + 1
        return self

    def dims(self) -> dict[str, int]:
        return {sym: int(self.attrs[a]) for sym, a in ATTR_DIMS if _is_int(self.attrs.get(a))}


def _link_exists(f, path: str) -> bool:
    """Whether ``path`` is linked in the file although h5py cannot open it (damage)."""
    try:
        parent, _, name = path.rpartition("/")
        g = f.get(parent) if parent else f
        return g is not None and hasattr(g, "keys") and name in list(g.keys())
    except Exception:  # noqa: BLE001
        return False


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))


def open_view(f, path="map", version: int | None = None) -> MapView:
    """Header check, then the file viewed through its own schema and migrated to ``version``."""
    ver = check_header(f.attrs, path)
    return MapView.from_file(f, ver).upgrade(version)


# -- structure --------------------------------------------------------------------------------------
def check_attributes(attrs: dict, version: int = FORMAT_VERSION, values: bool = False) -> list[str]:
    """Problems of the root attributes (types, constants, minima, provenance JSON). With ``values``
    also the cosmetic format checks (ISO date of ``created``, non-empty strings)."""
    problems = []
    for name, spec in load_schema(version)["attributes"].items():
        if name not in attrs:
            problems.append(f"missing root attribute {name!r}")
            continue
        v = attrs[name]
        if spec["type"] == "str":
            if not isinstance(v, str):
                problems.append(f"attribute {name!r} should be a string, not {type(v).__name__}")
                continue
            if spec.get("json") == "object":
                try:
                    obj = json.loads(v)
                except ValueError as e:
                    problems.append(f"attribute {name!r} is not valid JSON ({first_line(e)})")
                    continue
                if not isinstance(obj, dict):
                    problems.append(f"attribute {name!r} should be a JSON object, not {type(obj).__name__}")
            if values and spec.get("nonempty") and not v.strip():
                problems.append(f"attribute {name!r} is empty")
            if values and spec.get("format") == "date-time":
                try:
                    datetime.fromisoformat(v)
                except ValueError:
                    problems.append(f"attribute {name!r} = {v!r} is not an ISO 8601 date-time")
        elif spec["type"] == "int":
            if not _is_int(v):
                problems.append(f"attribute {name!r} should be an integer, not {type(v).__name__}")
                continue
            if "min" in spec and v < spec["min"]:
                problems.append(f"attribute {name!r} = {v} is below {spec['min']}")
        if "const" in spec and v != spec["const"]:
            problems.append(f"attribute {name!r} is {v!r}, expected {spec['const']!r}")
    return problems


def check_datasets(
    view: MapView, version: int = FORMAT_VERSION, h5: bool = True, broken: set | None = None
) -> list[str]:
    """Problems of dataset presence, dtype, shape (dimensions shared between datasets and with the
    attributes) and, for ``h5`` files, chunking with Fletcher-32. The paths whose content cannot be
    interpreted (missing, wrong dtype or shape) are added to ``broken``."""
    import h5py

    problems = []
    broken = set() if broken is None else broken
    dims = view.dims()
    for path, spec in load_schema(version)["datasets"].items():
        n_before = len(problems)
        obj = view.datasets.get(path)
        if obj is None and spec.get("optional"):
            continue
        if obj is None:
            problems.append(f"missing dataset {path!r}")
            broken.add(path)
            continue
        if isinstance(obj, str):
            problems.append(f"{path!r} {obj}")
            broken.add(path)
            continue
        want = spec["dtype"]
        try:
            dtype, shape = obj.dtype, tuple(obj.shape)
        except Exception as e:  # noqa: BLE001
            problems.append(f"{path!r} cannot be inspected ({first_line(e)})")
            broken.add(path)
            continue
        if want == "str":
            in_h5 = isinstance(obj, h5py.Dataset)
            if not (
                dtype.kind == "S"
                or (dtype.kind == "O" and (not in_h5 or h5py.check_string_dtype(dtype) is not None))
                or (dtype.kind == "U" and not in_h5)
            ):
                problems.append(f"{path!r} has dtype {dtype}, expected strings")
        elif dtype != np.dtype(want):
            problems.append(f"{path!r} has dtype {dtype}, expected {want}")
        want_shape = spec["shape"]
        if len(shape) != len(want_shape):
            problems.append(f"{path!r} has shape {shape}, expected {tuple(want_shape)}")
        else:
            for n, s in zip(shape, want_shape):
                if isinstance(s, int):
                    if n != s:
                        problems.append(f"{path!r} has shape {shape}, expected {tuple(want_shape)}")
                        break
                elif dims.setdefault(s, n) != n:
                    problems.append(f"{path!r} has {n} along {s!r} but the map has {dims[s]}")
                    break
        if len(problems) > n_before:
            broken.add(path)
        if h5 and isinstance(obj, h5py.Dataset):
            try:
                if obj.chunks is None or not obj.fletcher32:
                    problems.append(f"{path!r} has no Fletcher-32 checksum")
            except Exception as e:  # noqa: BLE001
                problems.append(f"{path!r} has an unreadable filter pipeline ({first_line(e)})")
    return problems


def check_structure(view: MapView, version: int = FORMAT_VERSION) -> list[str]:
    return check_attributes(view.attrs, version) + check_datasets(view, version)


def check_file(f, version: int = FORMAT_VERSION) -> list[str]:
    """All structural problems of an open h5py.File against the schema (empty list: valid). Files
    of older versions are checked after migration to ``version``."""
    try:
        view = open_view(f, getattr(f, "filename", "map"), version)
    except MapFormatError as e:
        return [str(e)]
    return check_structure(view, version)


# -- values (the constraints' checks: favormap.mapfile.value_checks) --------------------------------
def check_values(
    path: str, a: np.ndarray, dims: dict, arrays: dict | None = None, version: int = FORMAT_VERSION
) -> tuple[list[str], list[str]]:
    """(problems, warnings) of the ``values`` constraints of dataset ``path`` for its fully read
    array ``a``. ``arrays`` gives the other datasets (for ``in`` and ``consistent_with``)."""
    spec = load_schema(version)["datasets"][path].get("values", {})
    problems, warnings = [], []
    arrays = arrays or {}
    if not spec or a.size == 0:
        return problems, warnings
    af = cmp = a
    if a.dtype.kind == "f":
        problems += nonfinite_problems(path, a, spec)
        if any(k in spec for k in ("min", "max", "exclusive_min", "unit_norm", "ordered", "rigid")):
            af = a.astype(np.float64, copy=False)
            cmp = np.where(np.isnan(af), 0.0, af)  # NaN counted above, not again
    if a.dtype.kind in "fiu":
        problems += bound_problems(path, a, cmp, spec, dims)
        problems += row_problems(path, a, af, cmp, spec)
    problems += membership_problems(path, a, spec, arrays)
    if "consistent_with" in spec and arrays.get(spec["consistent_with"]) is not None:
        idx = np.asarray(arrays[spec["consistent_with"]], np.int64)
        idx = idx[(idx >= 0) & (idx < len(a))]
        bad = np.bincount(idx, minlength=len(a)) != a
        if bad.any():
            warnings.append(
                f"{path!r}: {count_values(bad)} differ from the number of observations in {spec['consistent_with']!r}"
            )
    return problems, warnings


def check_arrays(arrays: dict[str, np.ndarray], attrs: dict, version: int = FORMAT_VERSION) -> list[str]:
    """Structure and values of a map held in memory (``arrays`` keyed by schema path, ``attrs`` as
    written): what the writer checks before it creates any file."""
    view = MapView(dict(attrs), {p: np.asarray(a) for p, a in arrays.items()}, version)
    problems = check_attributes(attrs, version) + check_datasets(view, version, h5=False)
    if problems:
        return problems
    dims = view.dims()
    for p, a in view.datasets.items():
        problems += check_values(p, a, dims, view.datasets, version)[0]
    return problems
