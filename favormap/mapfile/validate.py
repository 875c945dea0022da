"""Full validation of a map file: every problem, never an exception.

:func:`validate` checks, in order, and collects every problem it finds:

1. the file: exists, is a file, is a readable HDF5 file (not truncated);
2. the header: magic ``format`` attribute, ``format_version`` (a newer version stops here);
3. the structure against the schema of the file's version, after migration to this version:
   attributes (types, constants, minima, JSON provenance, ISO date), datasets (presence, dtype,
   shape, dimensions shared between datasets and attributes, chunking + Fletcher-32);
4. integrity: every dataset is read fully, so every chunk's Fletcher-32 checksum is verified
   (corrupted landmark rows of the voxel grids are located);
5. values: the ``values`` constraints of the schema (finite numbers, unique non-zero ids, index
   ranges, positive voxel sizes, unit view directions, rigid poses, known camera models, ...).

Unknown extra datasets and observation-count mismatches are warnings, not problems.

The report carries the file's layout description (:mod:`favormap.mapfile.layout`) for any readable
HDF5 file; ``Report.to_dict`` (``favormap validate --json``) merges it into the report's fields,
which is what the JSON Schema ``schemas/favormap-map.v<N>.json`` validates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FavormapError, first_line
from .layout import describe_open
from .schema import (
    FORMAT,
    FORMAT_VERSION,
    MapView,
    check_attributes,
    check_datasets,
    check_header,
    check_values,
    load_schema,
)

_BLOCK_BYTES = 8 << 20  # read big datasets in blocks of about this size


@dataclass
class Report:
    path: str
    valid: bool = False
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    format_version: int | None = None
    reader_version: int = FORMAT_VERSION
    num_landmarks: int | None = None
    num_frames: int | None = None
    datasets_read: int = 0
    bytes_read: int = 0
    layout: dict | None = None  # the layout description; None when the file is no readable HDF5 file

    def to_dict(self) -> dict:
        """The report's fields and, when there is one, the layout description's ``attributes``,
        ``groups`` and ``datasets``: a JSON object the map schema validates."""
        d = asdict(self)
        layout = d.pop("layout")
        return {**d, **(layout or {})}


def _describe(e: BaseException) -> str:
    if isinstance(e, OSError):
        return f"checksum mismatch or read error ({first_line(e)})"
    return f"{type(e).__name__}: {first_line(e)}"


def _read_full(ds, path: str, spec: dict, report: Report) -> np.ndarray | None:
    """Read dataset ``ds`` completely (verifying every chunk's checksum); None on failure, after
    recording which rows are damaged."""
    try:
        n = len(ds) if ds.shape else 0
        row_bytes = int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize if ds.shape else ds.dtype.itemsize
    except Exception as e:  # noqa: BLE001
        report.problems.append(f"{path!r} cannot be read: {_describe(e)}")
        return None
    if not ds.shape or n == 0:
        try:
            a = ds[()]
        except Exception as e:  # noqa: BLE001
            report.problems.append(f"{path!r} cannot be read: {_describe(e)}")
            return None
        report.datasets_read += 1
        return np.asarray(a)
    step = max(1, _BLOCK_BYTES // max(1, row_bytes))
    chunk_rows = 1
    try:
        if ds.chunks:
            chunk_rows = ds.chunks[0]
    except Exception:  # noqa: BLE001
        pass
    step = max(chunk_rows, step - step % chunk_rows)
    out = np.empty(ds.shape, ds.dtype) if ds.dtype.kind != "O" else [None] * n
    bad_rows: list[tuple[int, int]] = []
    first_error = None
    for a in range(0, n, step):
        b = min(n, a + step)
        try:
            out[a:b] = ds[a:b]
            report.bytes_read += (b - a) * row_bytes
            continue
        except Exception as e:  # noqa: BLE001
            first_error = first_error or e
        # locate the damaged chunks inside the block
        for c in range(a, b, chunk_rows):
            d = min(b, c + chunk_rows)
            try:
                out[c:d] = ds[c:d]
                report.bytes_read += (d - c) * row_bytes
            except Exception as e:  # noqa: BLE001
                first_error = first_error or e
                if bad_rows and bad_rows[-1][1] == c:
                    bad_rows[-1] = (bad_rows[-1][0], d)
                else:
                    bad_rows.append((c, d))
    if first_error is not None:
        nbad = sum(d - c for c, d in bad_rows)
        where = ", ".join(f"{c}" if d == c + 1 else f"{c}-{d - 1}" for c, d in bad_rows[:8]) + (
            ", ..." if len(bad_rows) > 8 else ""
        )
        report.problems.append(f"{path!r}: {_describe(first_error)} in row(s) {where} ({nbad} of {n} rows damaged)")
        return None
    report.datasets_read += 1
    return np.asarray(out) if ds.dtype.kind != "O" else np.array(out, dtype=object)


def validate(path) -> Report:
    """Check a map file completely. Never raises for a bad file (see the module docstring)."""
    import h5py

    path = Path(path)
    report = Report(str(path))
    if not path.exists():
        report.problems.append(f"file not found: {path}")
        return report
    if path.is_dir():
        report.problems.append(f"{path} is a directory, not a map file")
        return report
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError as e:
        report.problems.append(f"{path} cannot be read ({first_line(e)})")
        return report
    if size == 0:
        report.problems.append(f"{path} is empty (0 bytes)")
        return report
    if head != b"\x89HDF\r\n\x1a\n":
        report.problems.append(f"{path} is not an HDF5 file, so not a favormap map (no HDF5 signature)")
        return report
    try:
        f = h5py.File(path, "r", locking=False)
    except Exception as e:  # noqa: BLE001
        if "truncated" in str(e):
            report.problems.append(f"{path} is truncated (an incompletely written or damaged HDF5 file)")
        else:
            report.problems.append(f"{path} is not a readable HDF5 file ({first_line(e)})")
        return report
    try:
        report.layout = describe_open(f)
    except Exception as e:  # noqa: BLE001
        report.problems.append(f"{path}: the layout cannot be listed ({type(e).__name__}: {first_line(e)})")
    try:
        _validate_open(f, path, report)
    except Exception as e:  # noqa: BLE001 - validation itself must never crash on a hostile file
        report.problems.append(f"{path}: unexpected damage, validation stopped ({type(e).__name__}: {first_line(e)})")
    finally:
        try:
            f.close()
        except Exception:  # noqa: BLE001
            pass
    report.valid = not report.problems
    return report


def _validate_open(f, path: Path, report: Report) -> None:
    # -- header
    try:
        version = check_header(f.attrs, path)
    except FavormapError as e:
        msg = str(e)
        report.problems.append(msg)
        ver = _raw_version(f.attrs)
        if ver is not None:
            report.format_version = ver  # a newer or invalid version is still the file's version
        if "reads up to" in msg:
            return  # an unknown future layout: nothing more can be checked
        groups = {p.split("/")[0] for p in load_schema(FORMAT_VERSION)["datasets"]}
        try:
            present = groups & set(f.keys())
        except Exception:  # noqa: BLE001
            present = set()
        if not present:
            return  # a foreign HDF5 file: listing every missing item would only be noise
        version = FORMAT_VERSION
    except Exception as e:  # noqa: BLE001
        report.problems.append(f"the file header cannot be read: {_describe(e)}")
        return
    report.format_version = _raw_version(f.attrs)
    # -- structure (through the file's own schema, migrated to this version)
    try:
        view = MapView.from_file(f, version).upgrade()
    except FavormapError as e:
        report.problems.append(str(e))
        return
    report.warnings += [f"unknown dataset or group {p!r} (ignored)" for p in view.extra]
    report.problems += check_attributes(view.attrs, values=True)
    broken: set[str] = set()
    report.problems += check_datasets(view, broken=broken)
    dims = view.dims()
    report.num_landmarks = dims.get("L")
    report.num_frames = dims.get("M")
    # -- integrity: read everything; values
    schema = load_schema(FORMAT_VERSION)
    arrays: dict[str, np.ndarray | None] = {}
    for p, spec in schema["datasets"].items():
        obj = view.datasets.get(p)
        if obj is None or isinstance(obj, str):
            continue
        if isinstance(obj, np.ndarray):
            arrays[p] = obj
            report.datasets_read += 1
        else:
            arrays[p] = _read_full(obj, p, spec, report)
    for p in schema["datasets"]:
        a = arrays.get(p)
        if a is None or p in broken:
            continue
        try:
            problems, warnings = check_values(p, a, dims, {k: v for k, v in arrays.items() if k not in broken})
        except Exception as e:  # noqa: BLE001
            problems, warnings = [f"{p!r}: values cannot be checked ({type(e).__name__}: {first_line(e)})"], []
        report.problems += problems
        report.warnings += warnings


def _raw_version(attrs) -> int | None:
    """The file's ``format_version`` attribute as an int, whatever its value; None when absent or
    not an integer."""
    try:
        v = attrs.get("format_version")
        v = v[()] if isinstance(v, np.ndarray) and v.shape == () else v
    except Exception:  # noqa: BLE001
        return None
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
        return None
    return int(v)


def format_report(r: Report) -> list[str]:
    """Human-readable lines for ``favormap validate``."""
    if r.valid:
        ver = f"favormap map v{r.format_version}" + (
            f", read as v{r.reader_version}" if r.format_version != r.reader_version else ""
        )
        lines = [
            f"{r.path}: valid ({ver}, {r.num_landmarks} landmarks, {r.num_frames} frames; "
            f"{r.datasets_read} datasets, {r.bytes_read} bytes read, checksums verified)"
        ]
    else:
        lines = [f"{r.path}: INVALID, {len(r.problems)} problem{'s' if len(r.problems) != 1 else ''}:"]
        lines += [f"  - {p}" for p in r.problems]
    lines += [f"  warning: {w}" for w in r.warnings]
    return lines


__all__ = ["FORMAT", "Report", "format_report", "validate"]
