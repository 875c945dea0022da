"""The one table of per-landmark datasets, read from the map schema (the single source of truth).

Every dataset of the schema whose first dimension is ``L`` holds one row per landmark; its name on
:class:`~favormap.mapfile.MapData` and :class:`~favormap.mapfile.Map` is the last part of its path
(``landmarks/quality`` -> ``quality``, ``voxels/density`` -> ``density``). Rows a few numbers wide
(no ``C`` or ``R`` in the shape) are *metadata*: the reader holds them in memory from the start, and
merge and prune copy them row by row. The others (mean descriptors, voxel grids) are *bulk*: read
on demand and streamed. Adding a per-landmark field to the schema is enough for read, write,
merge, prune and landmark selection to carry it (merge copies a new field unchanged: a field that
lives in world coordinates needs a rule in ``ops/merge.py``'s ``_to_first_frame``).
"""

from __future__ import annotations

from .schema import FORMAT_VERSION, load_schema

_BULK_SYMBOLS = {"C", "R"}


def landmark_datasets(version: int = FORMAT_VERSION) -> tuple[str, ...]:
    """Paths of the datasets with one row per landmark, in schema order."""
    return tuple(p for p, s in load_schema(version)["datasets"].items() if s["shape"] and s["shape"][0] == "L")


def metadata_datasets(version: int = FORMAT_VERSION) -> tuple[str, ...]:
    """Per-landmark datasets held in memory (ids, positions, quality, view cone, ...)."""
    ds = load_schema(version)["datasets"]
    return tuple(p for p in landmark_datasets(version) if not _BULK_SYMBOLS & set(map(str, ds[p]["shape"])))


def bulk_datasets(version: int = FORMAT_VERSION) -> tuple[str, ...]:
    """Per-landmark datasets read on demand and streamed (mean descriptors, voxel grids)."""
    meta = set(metadata_datasets(version))
    return tuple(p for p in landmark_datasets(version) if p not in meta)


def field_name(path: str) -> str:
    """The attribute name of a dataset path: its last part."""
    return path.rsplit("/", 1)[-1]
