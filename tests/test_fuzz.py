"""Property-based fuzzing of the map reader and validator (hypothesis, bounded).

A small valid map is written from random MapData; then its bytes are flipped, the file is truncated,
datasets are deleted or replaced with wrong dtypes/shapes, attributes are changed or deleted. For
every case, opening + reading everything + validating either succeeds (the damage hit nothing that
matters) or fails with a FavormapError carrying a non-empty one-line message - never another
exception. And whenever validate says "valid", reading must work.

Examples are derandomized by default (stable CI); set HYPOTHESIS_PROFILE=fuzz-random for new ones
and FAVORMAP_FUZZ_EXAMPLES=500 for a longer hunt.
"""

from __future__ import annotations

import itertools
import os
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_mapfile import random_map

from favormap.errors import FavormapError, MapFormatError
from favormap.mapfile import Map, load_schema, write_map
from favormap.mapfile.validate import validate

_common = dict(
    deadline=None,
    max_examples=int(os.environ.get("FAVORMAP_FUZZ_EXAMPLES", "30")),
    suppress_health_check=[HealthCheck.too_slow],
    database=None,
)
settings.register_profile("fuzz-ci", derandomize=True, **_common)
settings.register_profile("fuzz-random", **_common)
FUZZ = settings.get_profile(
    os.environ.get("HYPOTHESIS_PROFILE", "fuzz-ci")
    if os.environ.get("HYPOTHESIS_PROFILE", "").startswith("fuzz")
    else "fuzz-ci"
)

DATASETS = list(load_schema()["datasets"])
ATTRIBUTES = list(load_schema()["attributes"])

_dir = Path(tempfile.mkdtemp(prefix="favormap-fuzz-"))
_counter = itertools.count()


def teardown_module(module):
    shutil.rmtree(_dir, ignore_errors=True)


def _base() -> Path:
    p = _dir / "base.h5"
    if not p.exists():
        write_map(random_map(11, L=20, C=8, R=3, M=5), p)
    return p


BASE_BYTES = None


def base_bytes() -> bytes:
    global BASE_BYTES
    if BASE_BYTES is None:
        BASE_BYTES = _base().read_bytes()
    return BASE_BYTES


def fresh(data: bytes | None = None) -> Path:
    p = _dir / f"case{next(_counter)}.h5"
    p.write_bytes(base_bytes() if data is None else data)
    return p


def _chunk_ranges(path: Path, names) -> list[tuple[int, int]]:
    out = []
    with h5py.File(path, "r") as f:
        for name in names:
            ds = f[name]
            for i in range(ds.id.get_num_chunks()):
                info = ds.id.get_chunk_info(i)
                out.append((info.byte_offset, info.size))
    return out


def exercise(path: Path) -> tuple[bool, bool]:
    """Open + read everything, then validate. Returns (read_ok, valid); fails the test on any
    exception that is not a FavormapError or on an empty/multi-line message."""
    read_ok = True
    try:
        with Map.open(path) as m:
            n = len(m)
            m.voxels(np.arange(n))
            m.voxels(np.arange(n)[::-3])
            m.mean_descriptors(np.arange(n))
            m.tracks()
            m.info()
            m.load()
    except FavormapError as e:
        msg = str(e)
        assert msg.strip() and "\n" not in msg, repr(msg)
        read_ok = False
    r = validate(path)  # must never raise
    assert isinstance(r.valid, bool)
    assert r.valid == (not r.problems)
    assert all(isinstance(p, str) and p.strip() for p in r.problems)
    if r.valid:
        assert read_ok, "validate said valid but reading failed"
    path.unlink(missing_ok=True)
    return read_ok, r.valid


@FUZZ
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255)), min_size=1, max_size=12))
def test_random_byte_flips(flips):
    data = bytearray(base_bytes())
    for where, xor in flips:
        data[int(where * len(data))] ^= xor
    exercise(fresh(bytes(data)))


@FUZZ
@given(st.data())
def test_flips_inside_chunk_data_are_always_detected(data):
    """A damaged chunk of any dataset is caught by its Fletcher-32 checksum: never read silently."""
    base = _base()
    ranges = _chunk_ranges(base, DATASETS)
    off, size = data.draw(st.sampled_from(ranges))
    k = data.draw(st.integers(0, size - 1))
    xor = data.draw(st.integers(1, 255))
    buf = bytearray(base_bytes())
    buf[off + k] ^= xor
    read_ok, valid = exercise(fresh(bytes(buf)))
    assert not read_ok and not valid


@FUZZ
@given(st.integers(0, 10**9))
def test_truncation_is_always_refused(n):
    data = base_bytes()
    read_ok, valid = exercise(fresh(data[: n % len(data)]))
    assert not read_ok and not valid


_values = st.one_of(
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.binary(max_size=20),
    st.booleans(),
    st.lists(st.integers(-5, 5), min_size=0, max_size=4).map(np.array),
    st.sampled_from(["{}", "[]", '{"stats": 3}', "null", "not json", "favormap-map", "2024-01-01T00:00:00+00:00"]),
)

_dtypes = st.sampled_from(["int8", "uint16", "int32", "int64", "uint64", "float16", "float32", "float64", "S4", "bool"])


def _shape_variant(shape, choice: int):
    shape = list(shape)
    if choice == 0:
        return tuple(shape + [2])
    if choice == 1:
        return tuple(shape[:-1]) if len(shape) > 1 else (3, 3)
    if choice == 2:
        return tuple([shape[0] + 1] + shape[1:])
    return tuple([max(0, shape[0] - 1)] + shape[1:])


@FUZZ
@given(
    op=st.sampled_from(
        ["del_dataset", "dtype", "shape", "group", "del_attr", "set_attr", "del_group", "extra", "scalar"]
    ),
    dataset=st.sampled_from(DATASETS),
    attr=st.sampled_from(ATTRIBUTES),
    value=_values,
    dtype=_dtypes,
    shape_choice=st.integers(0, 3),
    checksum=st.booleans(),
)
def test_structural_edits(op, dataset, attr, value, dtype, shape_choice, checksum):
    p = fresh()
    must_fail = True
    with h5py.File(p, "r+") as f:
        if op == "del_dataset":
            del f[dataset]
        elif op in ("dtype", "shape", "scalar"):
            old = f[dataset]
            shape = old.shape if op == "dtype" else _shape_variant(old.shape, shape_choice) if op == "shape" else ()
            want = load_schema()["datasets"][dataset]["dtype"]
            dt = dtype if op == "dtype" else (old.dtype if want != "str" else "S8")
            del f[dataset]
            kw = dict(chunks=True, fletcher32=True) if checksum and shape and all(shape) else {}
            f.create_dataset(dataset, shape=shape, dtype=dt, **kw)
            if op == "dtype" and (np.dtype(dt) == old.dtype or (want == "str" and np.dtype(dt).kind == "S")):
                must_fail = False  # same dtype: zeros of the right shape may or may not be valid
        elif op == "group":
            del f[dataset]
            f.create_group(dataset)
        elif op == "del_group":
            del f[dataset.split("/")[0]]
        elif op == "del_attr":
            del f.attrs[attr]
        elif op == "set_attr":
            must_fail = False
            try:
                f.attrs[attr] = value
            except (TypeError, ValueError, OverflowError):
                f.attrs[attr] = "garbage"
        elif op == "extra":
            must_fail = False
            f.create_dataset(f"{dataset}_extra", data=np.arange(3))
    read_ok, valid = exercise(p)
    if must_fail:
        assert not read_ok and not valid, (op, dataset, attr)
    if op == "extra":
        assert read_ok and valid


@FUZZ
@given(
    dataset=st.sampled_from([d for d in DATASETS if load_schema()["datasets"][d]["dtype"] != "str"]),
    value=st.one_of(st.sampled_from([np.nan, np.inf, -np.inf, 0, -1, 1e30, 2**31 - 1]), st.floats(-1e6, 1e6)),
    frac=st.floats(0, 1, exclude_max=True),
)
def test_value_edits(dataset, value, frac):
    """Values that break the contract (NaN, out-of-range indices, duplicated ids, ...) are either
    harmless or refused; never a crash."""
    p = fresh()
    with h5py.File(p, "r+") as f:
        ds = f[dataset]
        a = ds[()]
        if a.size:
            flat = a.reshape(-1)
            with np.errstate(all="ignore"):
                try:
                    flat[int(frac * flat.size)] = value
                except (OverflowError, ValueError):
                    flat[int(frac * flat.size)] = 0
            ds[...] = a
    exercise(p)


def test_fuzz_helpers_see_a_valid_base():
    assert exercise(fresh()) == (True, True)
    assert len(_chunk_ranges(_base(), DATASETS)) >= len(DATASETS)


def test_every_error_is_a_map_format_error_for_damaged_maps():
    data = bytearray(base_bytes())
    off, size = _chunk_ranges(_base(), ["voxels/descriptors"])[3]
    data[off + 1] ^= 0x55
    p = fresh(bytes(data))
    with Map.open(p) as m:
        with pytest.raises(MapFormatError):
            m.voxels([3])
