"""The layout description of a map file: what ``schemas/favormap-map.v<N>.json`` (a JSON Schema)
validates and ``favormap validate --json`` prints.

The description is a plain dump, nothing interpreted, so any HDF5 file gets one (which the schema
then rejects when it is not a map)::

    {"attributes": {NAME: {"type": "str", "value": ..., "string": {"length": "variable", "encoding": "utf-8"}}
                    | {"type": "int", "value": ..., "dtype": "int64"} | {"type": "float", ...} | ...},
     "groups": [PATH, ...],
     "datasets": {PATH: {"dtype": "float32" | ... | "str", "string": {...} (strings only),
                         "shape": [...], "chunks": [...] | null, "compression": "gzip" | null,
                         "fletcher32": bool}}}

``tools/read_map_standalone.py --describe`` prints the same with h5py alone.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import MapFormatError, first_line


def _string_entry(tid) -> dict:
    """The HDF5 string type ``tid``: its length (bytes, or "variable") and its character set."""
    import h5py

    enc = "utf-8" if tid.get_cset() == h5py.h5t.CSET_UTF8 else "ascii"
    return {"length": "variable" if tid.is_variable_str() else int(tid.get_size()), "encoding": enc}


def _attribute_entry(attrs, name: str) -> dict:
    import h5py

    raw = attrs[name]
    tid = attrs.get_id(name).get_type()
    if isinstance(tid, h5py.h5t.TypeStringID):
        v = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
        return {"type": "str", "value": v, "string": _string_entry(tid)}
    a = np.asarray(raw)
    if a.shape == () and a.dtype.kind == "b":
        return {"type": "bool", "value": bool(a)}
    if a.shape == () and a.dtype.kind in "iu":
        return {"type": "int", "value": int(a), "dtype": a.dtype.name}
    if a.shape == () and a.dtype.kind == "f":
        v = float(a)
        return {"type": "float", "value": v if np.isfinite(v) else None, "dtype": a.dtype.name}
    return {"type": "other", "value": None}


def _dataset_entry(ds) -> dict:
    import h5py

    tid = ds.id.get_type()
    out = {"dtype": "str", "string": _string_entry(tid)} if isinstance(tid, h5py.h5t.TypeStringID) else {}
    if not out:
        out["dtype"] = ds.dtype.name
    out["shape"] = [int(n) for n in ds.shape]
    out["chunks"] = None if ds.chunks is None else [int(n) for n in ds.chunks]
    out["compression"] = ds.compression
    out["fletcher32"] = bool(ds.fletcher32)
    return out


def describe_open(f) -> dict:
    """The layout description of an open h5py.File (see the module docstring)."""
    import h5py

    out = {
        "attributes": {k: _attribute_entry(f.attrs, k) for k in sorted(f.attrs.keys())},
        "groups": [],
        "datasets": {},
    }

    def visit(name, obj):
        if isinstance(obj, h5py.Group):
            out["groups"].append(name)
        elif isinstance(obj, h5py.Dataset):
            out["datasets"][name] = _dataset_entry(obj)

    f.visititems(visit)
    return out


def describe_layout(path) -> dict:
    """The layout description of the map file ``path`` (see the module docstring); MapFormatError
    when it is not a readable HDF5 file."""
    import h5py

    path = Path(path)
    try:
        f = h5py.File(path, "r", locking=False)
    except Exception as e:  # noqa: BLE001 - h5py raises several types for a non-HDF5 file
        raise MapFormatError(f"{path} is not a readable HDF5 file ({first_line(e)})") from None
    with f:
        return describe_open(f)


__all__ = ["describe_layout", "describe_open"]
