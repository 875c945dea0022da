#!/usr/bin/env python
"""Benchmark of map operations on a large synthetic map (default 1,000,000 landmarks).

    python tools/bench_ops.py [--landmarks 1000000] [--channels 64] [--queries 50] [--ops] [--keep PATH]

1. A child process writes a synthetic map with a realistic layout (a 400 m x 400 m city block:
   landmarks on building facades and on the street, trained from 2-35 m, seen within 5-35 deg of
   their facade normal; 0.3 % seen from far away) through the streaming ``MapWriter`` (random
   float16 voxel grids, R=3, C channels; the in-memory ``write_map`` would need the whole 7 GB of
   float32 grids). Its time and peak memory are reported separately.
2. This process then times ``Map.open``, building the spatial index (KD-trees of the visibility
   tiers), visibility queries from street-level poses through the index (``visible_rows``) vs
   brute force (``visible_mask`` over every landmark; results compared, must be equal), frustum
   queries vs brute-force projection, reading the visible landmarks' voxel grids, and its own peak
   memory (VmHWM peak RSS; tracemalloc for Python-side allocations).
3. With ``--ops``: prune to 10 % and export to .ply, each in a child process (time, peak memory).

Targets: index query >= 10x faster than brute force; this process < 2 GB peak RSS.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

AREA = 400.0  # metres
BLOCK = 40.0  # street grid spacing
FOOT = 25.0  # building footprint side
CAMERA = dict(model="PINHOLE", width=640, height=480, params=[500.0, 500.0, 320.0, 240.0])


def _status_mb(key: str) -> float | None:
    """A memory line of /proc/self/status (MB), or None where there is none."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def peak_rss_mb() -> float:
    """Peak resident memory of this process (VmHWM: unlike ru_maxrss, not inherited from the
    parent across fork + exec, so child processes report their own peak)."""
    mb = _status_mb("VmHWM")
    return mb if mb is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def rss_mb() -> float:
    """Resident memory of this process now (VmRSS, MB); 0 where /proc is not there."""
    return _status_mb("VmRSS") or 0.0


# -------------------------------------------------------------------------------------------------
# synthetic map
# -------------------------------------------------------------------------------------------------
def landmark_layout(L: int, rng: np.random.Generator) -> dict:
    """Positions and training geometry of ``L`` landmarks in the city block."""
    nb = int(AREA // BLOCK)
    on_ground = rng.random(L) < 0.15
    pos = np.empty((L, 3))
    normal = np.zeros((L, 3))
    # facades: building (i, j) centred at (40 i + 20, 40 j + 20), one of its 4 sides, height 8-30 m
    n_f = int((~on_ground).sum())
    bi, bj = rng.integers(0, nb, n_f), rng.integers(0, nb, n_f)
    height = 8 + (np.sin(bi * 12.9898 + bj * 78.233) * 0.5 + 0.5) * 22
    side = rng.integers(0, 4, n_f)
    axis = side % 2  # 0: facade normal along x, 1: along y
    sign = np.where(side < 2, 1.0, -1.0)
    c = np.c_[bi * BLOCK + BLOCK / 2, bj * BLOCK + BLOCK / 2]
    along = rng.uniform(-FOOT / 2, FOOT / 2, n_f)
    p = np.empty((n_f, 3))
    p[:, 0] = np.where(axis == 0, c[:, 0] + sign * FOOT / 2, c[:, 0] + along)
    p[:, 1] = np.where(axis == 1, c[:, 1] + sign * FOOT / 2, c[:, 1] + along)
    p[:, 2] = rng.uniform(0, 1, n_f) * height
    nrm = np.zeros((n_f, 3))
    nrm[np.arange(n_f), axis] = sign
    pos[~on_ground], normal[~on_ground] = p, nrm
    # street surface: between the buildings
    n_g = int(on_ground.sum())
    g = rng.uniform(0, AREA, (n_g, 2))
    street_x = rng.random(n_g) < 0.5
    g[street_x, 0] = np.round(g[street_x, 0] / BLOCK) * BLOCK + rng.uniform(-7, 7, street_x.sum())
    g[~street_x, 1] = np.round(g[~street_x, 1] / BLOCK) * BLOCK + rng.uniform(-7, 7, (~street_x).sum())
    pos[on_ground] = np.c_[g, np.zeros(n_g)]
    normal[on_ground] = [0, 0, 1]
    # training views: around the normal, tilted towards the street level
    vd = normal + rng.normal(0, 0.25, (L, 3)) + [0, 0, -0.2]
    vd[on_ground] = normal[on_ground] + rng.normal(0, 0.5, (n_g, 3))
    vd /= np.linalg.norm(vd, axis=1, keepdims=True)
    dmin = rng.uniform(2, 10, L)
    dmax = dmin + rng.uniform(3, 25, L)
    far = rng.random(L) < 0.003
    dmax[far] = rng.uniform(60, 150, far.sum())
    return dict(
        positions=pos,
        view_dir=vd.astype(np.float32),
        view_angle=rng.uniform(5, 35, L).astype(np.float32),
        depth_range=np.c_[dmin, dmax].astype(np.float32),
        voxel_size=(7 * (dmin + dmax) / 2 / 500).astype(np.float32),
    )


def street_poses(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """cam_from_world of cameras 1.6 m above the streets, looking roughly horizontally."""
    from favormap.geometry import look_at

    out = []
    for _ in range(n):
        t = rng.uniform(BLOCK, AREA - BLOCK)
        k = rng.integers(1, int(AREA // BLOCK)) * BLOCK + rng.uniform(-5, 5)
        eye = np.array([k, t, 1.6]) if rng.random() < 0.5 else np.array([t, k, 1.6])
        yaw = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.1, 0.3)])
        out.append(look_at(eye, eye + d, up=(0, 0, 1)))
    return out


def write_synthetic(path: Path, L: int, C: int, R: int, n_frames: int, seed: int, chunk: int) -> dict:
    from favormap.io import Camera
    from favormap.mapfile import new_landmark_ids
    from favormap.mapfile.writer import MapWriter, camera_arrays

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    lay = landmark_layout(L, rng)
    track = (3 + rng.geometric(0.2, L)).astype(np.int32)
    O = int(track.sum())
    header = dict(
        extractor="xfeat",
        channels=C,
        grid_resolution=R,
        patch_size=7,
        render_samples=12,
        max_side=640,
        provenance={"synthetic": "tools/bench_ops.py", "seed": seed},
    )
    with MapWriter(path, header, L, n_frames) as w:
        w.put("landmarks/ids", new_landmark_ids(L))
        w.put("landmarks/positions", lay["positions"])
        for k in ("voxel_size", "view_dir", "view_angle", "depth_range"):
            w.put(f"landmarks/{k}", lay[k])
        w.put("landmarks/track_length", track)
        w.put("landmarks/reproj_error", rng.gamma(2, 0.4, L))
        w.put("landmarks/quality", rng.uniform(20, 42, L))
        w.put("landmarks/cosine", rng.uniform(0.8, 1, L))
        for k, v in camera_arrays({0: Camera.from_dict(CAMERA)}).items():
            w.put(k, v)
        w.put("frames/names", [f"frame_{i:06d}.png" for i in range(n_frames)])
        w.put("frames/camera_ids", np.zeros(n_frames, np.int32))
        w.put("frames/cam_from_world", np.stack(street_poses(n_frames, rng)))
        w.put("tracks/landmark_index", np.repeat(np.arange(L, dtype=np.int32), track))
        w.put("tracks/frame_index", rng.integers(0, n_frames, O).astype(np.int32))
        w.put("tracks/xy", rng.uniform(0, 480, (O, 2)).astype(np.float32))
        for k in ("voxels/descriptors", "voxels/density", "landmarks/mean_descriptor"):
            w.create(k)
        for a in range(0, L, chunk):
            n = min(chunk, L - a)
            d = rng.standard_normal((n, R**3, C), np.float32) * 0.2
            w.write_rows("voxels/descriptors", a, d)
            w.write_rows("voxels/density", a, rng.normal(0, 2, (n, R**3)).astype(np.float32))
            w.write_rows("landmarks/mean_descriptor", a, d.mean(1))
    return {
        "write_s": time.perf_counter() - t0,
        "write_peak_rss_mb": peak_rss_mb(),
        "observations": O,
        "file_size_gb": path.stat().st_size / 1e9,
    }


# -------------------------------------------------------------------------------------------------
# measurements
# -------------------------------------------------------------------------------------------------
def timed(fn, *a, repeat: int = 1, **k):
    best, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*a, **k)
        best.append(time.perf_counter() - t)
    return out, best


def bench_queries(path: Path, n_queries: int, seed: int) -> tuple[list, dict]:
    from favormap.io import Camera, working_camera
    from favormap.mapfile import Map
    from favormap.ops.spatial import SpatialIndex, ViewLimits, project_inside, visible_mask, visible_rows

    rows = []
    tracemalloc.start()
    rss0 = peak_rss_mb()
    m, t = timed(Map.open, path)
    rows.append(("Map.open (metadata, schema check)", t[0] * 1e3, ""))
    idx, t1 = timed(SpatialIndex, m.positions)
    _, t2 = timed(idx.prepare_visibility, m.depth_range, 2.0, m.view_dir, m.view_angle)
    tiers = idx._tiers
    rows.append(
        (
            "build index (KD-trees of the reach tiers)",
            (t1[0] + t2[0]) * 1e3,
            f"{len(tiers.tiers) - (tiers.num_direct > 0)} tiers, {tiers.num_direct} tested directly",
        )
    )
    _, t3 = timed(lambda: idx._tree)
    rows.append(("build index (one KD-tree, radius/knn)", t3[0] * 1e3, ""))
    cam = working_camera(Camera.from_dict(CAMERA), m.max_side)
    poses = street_poses(n_queries, np.random.default_rng(seed + 1))
    lim = ViewLimits()
    t_idx, t_bf, t_fr, t_frbf, n_vis, n_cand, t_vox = [], [], [], [], [], [], []
    for T in poses:
        r_idx, t = timed(visible_rows, idx, cam, T, m.view_dir, m.view_angle, m.depth_range, lim, repeat=3)
        t_idx.append(min(t))
        r_bf, t = timed(
            lambda T=T: np.flatnonzero(visible_mask(m.positions, cam, T, m.view_dir, m.view_angle, m.depth_range, lim)),
            repeat=2,
        )
        t_bf.append(min(t))
        if not np.array_equal(r_idx, r_bf):
            raise SystemExit(f"visible_rows differs from brute force ({len(r_idx)} vs {len(r_bf)})")
        n_vis.append(len(r_idx))
        n_cand.append(len(tiers.candidates(cam, T)[0]))
        f_idx, t = timed(idx.frustum, cam, T, 30.0, repeat=3)
        t_fr.append(min(t))
        f_bf, t = timed(lambda T=T: np.flatnonzero(project_inside(m.positions, cam, T, 0.0, 30.0)), repeat=2)
        t_frbf.append(min(t))
        if not np.array_equal(f_idx, f_bf):
            raise SystemExit("frustum differs from brute force")
        _, t = timed(m.voxels, r_idx)
        t_vox.append(t[0])
    med = lambda v: float(np.median(v)) * 1e3  # noqa: E731
    rows.append(
        (
            "visibility query, index (visible_rows)",
            med(t_idx),
            f"median of {n_queries}; {int(np.median(n_vis))} visible, {int(np.median(n_cand))} candidates tested",
        )
    )
    rows.append(
        (
            "visibility query, brute force (all landmarks)",
            med(t_bf),
            f"speed-up x{np.median(t_bf) / np.median(t_idx):.1f} (identical results)",
        )
    )
    rows.append(("frustum query 0-30 m, index", med(t_fr), ""))
    rows.append(
        (
            "frustum query 0-30 m, brute-force projection",
            med(t_frbf),
            f"speed-up x{np.median(t_frbf) / np.median(t_fr):.1f} (identical results)",
        )
    )
    rows.append(
        ("read voxel grids of the visible landmarks", med(t_vox), f"{m.bytes_read / 1e6 / n_queries:.1f} MB per query")
    )
    _, py_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    mem = {"peak_rss_mb": peak_rss_mb(), "rss_before_open_mb": rss0, "tracemalloc_peak_mb": py_peak / 1e6}
    m.close()
    return rows, mem


def child(kind: str, args) -> dict:
    """Run one measured operation in this (child) process; print a JSON line."""
    t = time.perf_counter()
    if kind == "write":
        out = write_synthetic(Path(args.path), args.landmarks, args.channels, 3, args.frames, args.seed, args.chunk)
    elif kind == "prune":
        from favormap.ops.prune import prune_map

        res = prune_map(args.path, args.out, max_landmarks=args.landmarks // 10)
        out = {"kept": res.num_after}
    elif kind == "export":
        from favormap.ops.export import export_landmarks

        res = export_landmarks(args.path, args.out)
        out = {"points": res.num_points}
    else:
        raise SystemExit(f"unknown child {kind}")
    out.update(seconds=time.perf_counter() - t, peak_rss_mb=peak_rss_mb())
    print(json.dumps(out))
    return out


def run_child(kind: str, path: Path, args, out: Path | None = None) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--path",
        str(path),
        "--landmarks",
        str(args.landmarks),
        "--channels",
        str(args.channels),
        "--frames",
        str(args.frames),
        "--seed",
        str(args.seed),
        "--chunk",
        str(args.chunk),
    ]
    if out is not None:
        cmd += ["--out", str(out)]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{kind} failed:\n{p.stderr}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--landmarks", type=int, default=1_000_000)
    ap.add_argument("--channels", type=int, default=64)
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--queries", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--chunk", type=int, default=8192)
    ap.add_argument("--ops", action="store_true", help="also time prune and export (child processes)")
    ap.add_argument("--keep", metavar="PATH", help="write (or reuse) the map here and keep it")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--path", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args)
        return 0

    tmpdir = tempfile.mkdtemp(prefix="favormap_bench_")
    path = Path(args.keep) if args.keep else Path(tmpdir) / "bench.h5"
    need = args.landmarks * 27 * (args.channels * 2 + 4) * 1.1
    free = os.statvfs(path.parent).f_bavail * os.statvfs(path.parent).f_frsize
    print(
        f"# {args.landmarks} landmarks, R=3, C={args.channels}: about {need / 1e9:.1f} GB of voxels; "
        f"{free / 1e9:.0f} GB free in {path.parent}"
    )
    if need > 0.8 * free:
        raise SystemExit("not enough disk space: use fewer --channels or --landmarks")
    table = []
    try:
        if not path.exists():
            w = run_child("write", path, args)
            table.append(
                (
                    "write synthetic map (streaming MapWriter)",
                    w["seconds"] * 1e3,
                    f"{w['file_size_gb']:.2f} GB, {w['observations']} observations, peak RSS {w['peak_rss_mb']:.0f} "
                    "MB (child)",
                )
            )
        rows, mem = bench_queries(path, args.queries, args.seed)
        table += rows
        if args.ops:
            for kind, out in (("prune", Path(tmpdir) / "pruned.h5"), ("export", Path(tmpdir) / "landmarks.ply")):
                r = run_child(kind, path, args, out)
                what = f"to {r['kept']} landmarks" if kind == "prune" else f"{r['points']} points to .ply"
                table.append((f"{kind} {what} (child)", r["seconds"] * 1e3, f"peak RSS {r['peak_rss_mb']:.0f} MB"))
    finally:
        if not args.keep:
            for f in Path(tmpdir).glob("*"):
                f.unlink()
            os.rmdir(tmpdir)
    w = max(len(r[0]) for r in table)
    print(f"{'step':<{w}}  {'ms':>10}  details")
    for name, ms, note in table:
        print(f"{name:<{w}}  {ms:10.1f}  {note}")
    print(
        f"peak RSS of the query process: {mem['peak_rss_mb']:.0f} MB (after imports {mem['rss_before_open_mb']:.0f} "
        "MB); "
        f"Python allocations peak (tracemalloc) {mem['tracemalloc_peak_mb']:.0f} MB"
    )
    ok_speed = any(
        "speed-up" in r[2] and float(r[2].split("x")[1].split()[0]) >= 10
        for r in rows
        if r[0].startswith("visibility query, brute")
    )
    print(
        f"targets: query >= 10x brute force: {'yes' if ok_speed else 'NO'}; peak RSS < 2 GB: "
        f"{'yes' if mem['peak_rss_mb'] < 2048 else 'NO'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
