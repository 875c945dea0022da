#!/usr/bin/env python3
"""Reference reader of the favormap map format, in NumPy and h5py alone (no favormap, no torch).

It follows docs/map-format.md step by step, for programs that read favormap maps without favormap
(a C++ robot stack, a ROS node, another toolkit): load a map's header and landmarks, read the voxel
grids of some landmarks, render their descriptors for any rays or from a camera centre, and dump the
file's layout description (what schemas/favormap-map.v1.json, a JSON Schema, validates).

Command line::

    python tools/read_map_standalone.py MAP.h5 --landmark 0 --camera X Y Z
    python tools/read_map_standalone.py MAP.h5 --landmark 0 --origin X Y Z --direction DX DY DZ
    python tools/read_map_standalone.py MAP.h5 --describe

Everything is computed in float64. This file must import nothing but NumPy, h5py and the standard
library.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field

import h5py
import numpy as np

FORMAT = "favormap-map"
READS_UP_TO = 1  # the newest map format version this reader knows


class MapReadError(Exception):
    """A file this reader cannot read as a favormap map (one line)."""


def _attr(v):
    """An HDF5 attribute as a plain Python value (strings decoded, numpy scalars unwrapped)."""
    if isinstance(v, bytes):
        return v.decode("utf-8")
    if isinstance(v, np.ndarray) and v.shape == ():
        v = v[()]
    if isinstance(v, np.generic):
        return v.item()
    return v


def _strings(a) -> list[str]:
    """A string dataset (fixed-length, null-padded bytes holding UTF-8) as Python strings."""
    return [s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in np.asarray(a).ravel().tolist()]


@dataclass
class StandaloneMap:
    """A map's root attributes and per-landmark metadata (voxel grids: :func:`read_grids`)."""

    path: str
    attrs: dict
    ids: np.ndarray  # (L,) uint64
    positions: np.ndarray  # (L, 3) float64, box centres, world frame
    voxel_size: np.ndarray  # (L,) float64, box sides, scene units
    view_dir: np.ndarray  # (L, 3)
    depth_range: np.ndarray  # (L, 2)
    frame_names: list[str] = field(default_factory=list)
    cam_from_world: np.ndarray | None = None  # (M, 4, 4)

    @property
    def grid_resolution(self) -> int:
        return int(self.attrs["grid_resolution"])

    @property
    def channels(self) -> int:
        return int(self.attrs["channels"])

    @property
    def render_samples(self) -> int:
        return int(self.attrs["render_samples"])


def _open(path) -> h5py.File:
    try:
        f = h5py.File(path, "r", locking=False)
    except (OSError, ValueError) as e:
        raise MapReadError(f"{path}: not a readable HDF5 file ({str(e).splitlines()[0] if str(e) else e})") from None
    fmt = _attr(f.attrs.get("format"))
    if fmt != FORMAT:
        f.close()
        raise MapReadError(f"{path}: not a favormap map (format attribute {fmt!r})")
    ver = _attr(f.attrs.get("format_version"))
    if not isinstance(ver, int) or ver > READS_UP_TO:
        f.close()
        raise MapReadError(f"{path}: map format version {ver!r}, this reader reads up to {READS_UP_TO}")
    return f


def load_map(path) -> StandaloneMap:
    """Root attributes, per-landmark metadata and frame poses of a map file."""
    with _open(path) as f:
        return StandaloneMap(
            path=str(path),
            attrs={k: _attr(v) for k, v in f.attrs.items()},
            ids=f["landmarks/ids"][()],
            positions=f["landmarks/positions"][()].astype(np.float64),
            voxel_size=f["landmarks/voxel_size"][()].astype(np.float64),
            view_dir=f["landmarks/view_dir"][()].astype(np.float64),
            depth_range=f["landmarks/depth_range"][()].astype(np.float64),
            frame_names=_strings(f["frames/names"][()]),
            cam_from_world=f["frames/cam_from_world"][()],
        )


def read_grids(path, rows) -> tuple[np.ndarray, np.ndarray]:
    """Node descriptors (n, R, R, R, C) and raw densities (n, R, R, R), float64, of landmark rows
    ``rows``; grid axes (x, y, z) of the world frame, node (0, 0, 0) at the box's min corner."""
    rows = np.asarray(rows, np.int64).ravel()
    with _open(path) as f:
        dd, ds = f["voxels/descriptors"], f["voxels/density"]
        if len(rows) and (rows.min() < 0 or rows.max() >= dd.shape[0]):
            raise MapReadError(f"{path}: landmark row out of range 0..{dd.shape[0] - 1}")
        order = np.unique(rows)  # h5py reads increasing unique indices
        inv = np.searchsorted(order, rows)
        desc = dd[order].astype(np.float64)[inv] if len(rows) else np.zeros((0,) + dd.shape[1:])
        dens = ds[order].astype(np.float64)[inv] if len(rows) else np.zeros((0,) + ds.shape[1:])
    return desc, dens


def _hats(g: np.ndarray, R: int) -> np.ndarray:
    """Hat weights h(g - i) = max(0, 1 - |g - i|) of grid coordinates g (...), nodes i last: (..., R)."""
    return np.maximum(1.0 - np.abs(g[..., None] - np.arange(R)), 0.0)


def render_rays(desc, dens, centers, sizes, origins, directions, n_samples: int, normalize: bool = True):
    """Descriptors (n, K, C) of K rays per landmark (docs/map-format.md, "Rendering").

    desc (n, R, R, R, C) and dens (n, R, R, R) as :func:`read_grids` returns them; centers (n, 3),
    sizes (n,) the boxes; origins and directions (n, K, 3) in the world frame (directions of any
    length). With ``normalize`` each descriptor is divided by max(its L2 norm, 1e-12). Also returns
    the rays' opacities (n, K)."""
    desc = np.asarray(desc, np.float64)
    dens = np.asarray(dens, np.float64)
    centers = np.asarray(centers, np.float64).reshape(-1, 1, 3)
    sizes = np.asarray(sizes, np.float64).reshape(-1, 1, 1)
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    R, N = desc.shape[1], int(n_samples)
    # 1. local frame: the box is [0, 1]^3, one unit per box side; unit direction
    p0 = (origins - centers) / sizes + 0.5
    v = directions / np.maximum(np.linalg.norm(directions, axis=-1, keepdims=True), 1e-12)
    # 2. entry and exit (slab test)
    inv = 1.0 / np.where(np.abs(v) < 1e-12, 1e-12, v)
    t0, t1 = (0.0 - p0) * inv, (1.0 - p0) * inv
    t_near = np.maximum(np.minimum(t0, t1).max(-1), 0.0)
    t_far = np.maximum(t0, t1).min(-1)
    hit = t_far > t_near + 1e-9
    chord = np.maximum(t_far - t_near, 0.0)
    # 3. samples at the midpoints of N equal parts of the chord, delta apart (in box sides)
    t = t_near[..., None] + chord[..., None] * ((np.arange(N) + 0.5) / N)  # (n, K, N)
    p = np.clip(p0[..., None, :] + t[..., None] * v[..., None, :], 0.0, 1.0)  # (n, K, N, 3)
    delta = chord / N
    # 4. trilinear interpolation: the product of the three 1D hats at g = p (R - 1)
    g = p * (R - 1)
    hx, hy, hz = _hats(g[..., 0], R), _hats(g[..., 1], R), _hats(g[..., 2], R)  # (n, K, N, R)
    raw = np.einsum("bkni,bknj,bknl,bijl->bkn", hx, hy, hz, dens, optimize=True)
    # 5. density activation after interpolation: sigma = softplus(raw), per box side
    sigma = np.logaddexp(0.0, raw)
    # 6. compositing
    alpha = 1.0 - np.exp(-sigma * delta[..., None])
    factors = np.ones_like(alpha)
    factors[..., 1:] = 1.0 - alpha[..., :-1] + 1e-10
    w = np.cumprod(factors, axis=-1) * alpha * hit[..., None]  # (n, K, N)
    d = np.einsum("bkn,bkni,bknj,bknl,bijlc->bkc", w, hx, hy, hz, desc, optimize=True)
    # 7. normalisation
    if normalize:
        d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    return d, w.sum(-1)


def render_from_camera(desc, dens, centers, sizes, camera_center, n_samples: int, normalize: bool = True):
    """Descriptors (n, C) of each landmark along the ray from ``camera_center`` (3,) through its box
    centre: what favormap renders to localize a camera at that centre."""
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    cam = np.broadcast_to(np.asarray(camera_center, np.float64).reshape(1, 1, 3), (len(centers), 1, 3))
    d, _ = render_rays(desc, dens, centers, sizes, cam, centers[:, None, :] - cam, n_samples, normalize)
    return d[:, 0]


# -- layout description (validated by schemas/favormap-map.v1.json) -----------------------------------
def _string_entry(tid) -> dict:
    """The HDF5 string type ``tid``: fixed length (bytes, null padded) or variable, and its character set."""
    enc = "utf-8" if tid.get_cset() == h5py.h5t.CSET_UTF8 else "ascii"
    return {"length": "variable" if tid.is_variable_str() else int(tid.get_size()), "encoding": enc}


def _dtype_entry(obj) -> dict:
    tid = obj.id.get_type()
    if isinstance(tid, h5py.h5t.TypeStringID):
        return {"dtype": "str", "string": _string_entry(tid)}
    return {"dtype": obj.dtype.name}


def _describe_attr(f, name: str) -> dict:
    v = _attr(f.attrs[name])
    tid = f.attrs.get_id(name).get_type()
    if isinstance(tid, h5py.h5t.TypeStringID):
        return {"type": "str", "value": v if isinstance(v, str) else str(v), "string": _string_entry(tid)}
    if isinstance(v, bool):
        return {"type": "bool", "value": v}
    if isinstance(v, int):
        return {"type": "int", "value": v, "dtype": f.attrs[name].dtype.name}
    if isinstance(v, float):
        return {"type": "float", "value": v if np.isfinite(v) else None, "dtype": f.attrs[name].dtype.name}
    return {"type": "other", "value": None}


def describe(path) -> dict:
    """The layout description of a map file: root attributes (type and value), groups, and every
    dataset's dtype, shape, chunks, compression and checksum flag. Nothing is interpreted: a foreign
    HDF5 file gets its description too (which the schema then rejects)."""
    try:
        f = h5py.File(path, "r", locking=False)
    except (OSError, ValueError) as e:
        raise MapReadError(f"{path}: not a readable HDF5 file ({str(e).splitlines()[0] if str(e) else e})") from None
    with f:
        out = {"attributes": {k: _describe_attr(f, k) for k in sorted(f.attrs.keys())}, "groups": [], "datasets": {}}

        def visit(name, obj):
            if isinstance(obj, h5py.Group):
                out["groups"].append(name)
            elif isinstance(obj, h5py.Dataset):
                out["datasets"][name] = {
                    **_dtype_entry(obj),
                    "shape": [int(n) for n in obj.shape],
                    "chunks": None if obj.chunks is None else [int(n) for n in obj.chunks],
                    "compression": obj.compression,
                    "fletcher32": bool(obj.fletcher32),
                }

        f.visititems(visit)
    return out


# -- command line ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("map", help="favormap map file (HDF5)")
    ap.add_argument("--landmark", type=int, action="append", default=[], help="landmark row (repeatable)")
    ap.add_argument("--camera", type=float, nargs=3, metavar=("X", "Y", "Z"), help="camera centre (world)")
    ap.add_argument("--origin", type=float, nargs=3, metavar=("X", "Y", "Z"), help="ray origin (world)")
    ap.add_argument("--direction", type=float, nargs=3, metavar=("DX", "DY", "DZ"), help="ray direction")
    ap.add_argument("--samples", type=int, help="samples per ray (default: the map's render_samples)")
    ap.add_argument("--raw", action="store_true", help="do not normalise the descriptors")
    ap.add_argument("--describe", action="store_true", help="print the map's layout description (JSON)")
    args = ap.parse_args(argv)
    try:
        if args.describe:
            print(json.dumps(describe(args.map), indent=1))
            return 0
        if not args.landmark or (args.camera is None) == (args.origin is None):
            raise MapReadError("give --landmark and either --camera or --origin with --direction")
        if args.origin is not None and args.direction is None:
            raise MapReadError("--origin needs --direction")
        m = load_map(args.map)
        n = args.samples or m.render_samples
        if n < 1:
            raise MapReadError("--samples must be at least 1")
        rows = np.asarray(args.landmark, np.int64)
        desc, dens = read_grids(args.map, rows)
        c, s = m.positions[rows], m.voxel_size[rows]
        if args.camera is not None:
            d = render_from_camera(desc, dens, c, s, args.camera, n, not args.raw)
        else:
            o = np.broadcast_to(np.asarray(args.origin, np.float64), (len(rows), 1, 3))
            v = np.broadcast_to(np.asarray(args.direction, np.float64), (len(rows), 1, 3))
            d = render_rays(desc, dens, c, s, o, v, n, not args.raw)[0][:, 0]
        print(json.dumps({"landmarks": rows.tolist(), "descriptors": d.tolist()}))
        return 0
    except (MapReadError, KeyError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
