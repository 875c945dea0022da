#!/usr/bin/env python3
"""Warm per-query localization time, split by stage, on a synthetic room map at 640x480 — and the
same queries against a map of a million landmarks around that room.

    python tools/bench_localize.py [--map MAP.h5] [--queries 10] [--passes 3] [--large 1000000] [--large-map BIG.h5]

Without --map, renders a 30-frame 640x480 synthetic room, builds a map with up to 1500 landmarks
and localizes held-out views from priors perturbed by 0.3 units / 15 degrees.

``--large N`` (default 1,000,000; 0: off) also writes a map of N landmarks: the room map plus
copies of it (landmarks, voxels, view ranges) on a square grid spaced so far apart that none of
them is visible from the room (a city block of rooms), and localizes the same queries against it.
Each map is measured in a fresh process, so that the peak RSS is the map's (VmHWM of the process:
extractor, map metadata, spatial index, voxel cache). The queries are localized ``--passes`` times
with the same priors (the first pass also fills the voxel cache and the allocator's free lists); the
per-query time is the median pass's mean, the stage times the mean over all passes, and each pass's
mean is printed below the table. The table gives the per-query time, the peak
RSS, the voxel bytes read per query (lazy loading: only visible landmarks' grids are read) and the
ratios large / room (target: both <= 2). ``--large-map`` keeps (or reuses) the large map's file.

``--split NAME`` measures a real split of tools/bench_accuracy.py instead (e.g. tum-desk-xyz; its map
built with the defaults, or ``--refine-poses``, and reused from ``--workdir`` as the accuracy benchmark
reuses it): every query localized by one warm Localizer from the nearest mapping frame (after a first
pass that warms the voxel cache), the queries as a stream (``localize_sequence``: each prior from the
poses before it), and the pycolmap-SIFT baseline built from the same mapping frames, in the same run.
favormap and the baseline take turns in blocks of 10 queries, so that a machine whose speed drifts
within minutes slows both alike. The table gives median milliseconds per query and stage, each mode's
ratio to the baseline's queries of its own turns, and the median (range) of that ratio over the blocks.

    python tools/bench_localize.py --split tum-desk-xyz --workdir /tmp/favormap-bench-accuracy
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_ops import peak_rss_mb, rss_mb  # tools/ is this script's first path entry


def write_tiled(src: Path, dst: Path, target: int) -> dict:
    """The map ``src`` and copies of it, translated on a square grid (copy 0 = the original in place),
    up to ``target`` landmarks or more. Spacing: the room's extent plus 8 times its largest training
    distance, so every copy is beyond the reach of the localizer's view limits (4x) from the room."""
    from favormap.mapfile import Map, new_landmark_ids
    from favormap.mapfile.writer import MapWriter, map_arrays, map_header

    t = time.perf_counter()
    m = Map.open(src).load()
    n = m.num_landmarks
    copies = max(1, math.ceil(target / n))
    side = math.ceil(math.sqrt(copies))
    extent = float(np.ptp(m.positions, axis=0).max())
    spacing = 2 * extent + 8 * float(m.depth_range[:, 1].max())
    g = np.array([(i % side, i // side) for i in range(copies)], np.float64) * spacing
    offsets = np.zeros((copies, 3))
    offsets[:, 0], offsets[:, 2] = g[:, 0], g[:, 1]
    arrays = map_arrays(m)
    streamed = ("voxels/descriptors", "voxels/density", "landmarks/mean_descriptor")
    L = copies * n
    with MapWriter(dst, map_header(m), L, m.num_frames) as w:
        for k, v in arrays.items():
            if k in streamed:
                continue
            v = np.asarray(v) if not isinstance(v, list) else v
            if k == "landmarks/ids":
                w.put(k, new_landmark_ids(L))
            elif k == "landmarks/positions":
                w.put(k, (v[None] + offsets[:, None]).reshape(-1, 3))
            elif k == "tracks/landmark_index":
                w.put(k, (v[None].astype(np.int64) + n * np.arange(copies)[:, None]).ravel())
            elif k.startswith(("landmarks/", "tracks/")):
                w.put(k, np.concatenate([v] * copies))
            else:
                w.put(k, v)
        for k in streamed:
            w.create(k)
            v = arrays[k]
            for c in range(copies):
                w.write_rows(k, c * n, v)
    return {
        "landmarks": L,
        "copies": copies,
        "spacing": spacing,
        "write_s": time.perf_counter() - t,
        "file_gb": dst.stat().st_size / 1e9,
    }


def measure(args) -> dict:
    """Localize the queries against one map (this process measures only that map)."""
    from favormap.geometry import perturb_pose, pose_error
    from favormap.io import read_sequence
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.synthetic import make_room, random_views_near, render

    seq = read_sequence(args.sequence)
    scene = make_room(0)
    cam = seq.cameras[0]
    views = random_views_near([f.cam_from_world for f in seq.frames], args.queries, seed=1, scene=scene)
    images = [render(scene, cam, T)[0] for T in views]
    t = time.perf_counter()
    loc = Localizer(
        args.measure, LocalizeConfig(device=args.device, descriptors=args.descriptors, threads=localize_threads(args))
    )
    open_s = time.perf_counter() - t
    rng = np.random.default_rng(0)
    loc.localize(images[0], perturb_pose(views[0], 0.3, 15, rng))  # warm-up (model, caches, KD-trees)
    priors = [perturb_pose(T, 0.3, 15, rng) for T in views]
    rows, errs, iters, ok, pass_ms = [], [], [], 0, []
    b0 = loc.map.bytes_read
    for p in range(args.passes):  # the same queries and priors in every pass; the figures of the first
        totals = []
        for img, T, prior in zip(images, views, priors):
            t = time.perf_counter()
            res = loc.localize(img, prior)
            totals.append(time.perf_counter() - t)
            rows.append(res.timings)
            if p == 0:
                iters.append([it.kind for it in res.iterations])
                errs.append(pose_error(res.cam_from_world, T))
                ok += bool(res.success)
        pass_ms.append(1000 * float(np.mean(totals)))
        if p == 0:
            kb = (loc.map.bytes_read - b0) / len(views) / 1024
    e = np.array(errs)
    return {
        "map": str(args.measure),
        "landmarks": len(loc.map),
        "open_s": open_s,
        "stages_ms": {k: 1000 * float(np.mean([r[k] for r in rows])) for k in rows[0]},  # over all passes
        "total_ms": float(np.median(pass_ms)),  # median over the passes of the mean per query
        "pass_ms": pass_ms,
        "localized": ok,
        "queries": len(views),
        "median_error": [float(np.median(e[:, 0])), float(np.median(e[:, 1]))],
        "voxel_kb_per_query": kb,
        "peak_rss_mb": peak_rss_mb(),
        # iterations per query: rendering ones, and how many queries ended with the guided step
        "render_iterations": float(np.mean([sum(k == "render" for k in i) for i in iters])),
        "guided": int(sum("guided" in i for i in iters)),
    }


# queries a block: favormap's blocks and the baseline's alternate, so that both see the machine alike
BLOCK = 10


def real_split_timing(args) -> int:
    """``--split``: warm, stream and baseline time per query on a real split (see the module docstring)."""
    from accuracy.runners import build_or_load
    from accuracy.splits import real_splits

    from favormap.build import BuildConfig
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.baseline import StructureBaseline
    from favormap.localize.evaluate import EvalConfig, make_priors
    from favormap.mapfile import Map

    splits = real_splits([args.split])
    if not splits:
        print(f"--split {args.split}: no such split, or its data is missing", file=sys.stderr)
        return 1
    sp = splits[0]
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    cfg = BuildConfig(refine_poses=args.refine_poses)
    path, build_s = build_or_load(sp, workdir, cfg, True, "-refine-poses" if args.refine_poses else "")
    m = Map.open(path)
    loc = Localizer(m, LocalizeConfig(device=args.device, threads=localize_threads(args)))
    frames = sp.queries.frames
    cams = [sp.queries.cameras[f.camera_id] for f in frames]
    priors = make_priors(sp.queries, m.rig_from_world, EvalConfig(prior_mode="nearest"))
    stages = ("extraction", "visibility", "loading", "rendering", "matching", "pnp")
    t = time.perf_counter()
    base = StructureBaseline.build(sp.mapping, workdir=workdir / f"{sp.files}_baseline")
    base_build = time.perf_counter() - t
    blocks = [range(a, min(a + BLOCK, len(frames))) for a in range(0, len(frames), BLOCK)]

    def row(res, wall):
        return [1000 * res.timings.get(k, 0.0) for k in stages] + [1000 * wall, res.success]

    def baseline_block(block, untimed_first=False):
        if untimed_first:  # takes the machine beside the stream's next extraction, which runs meanwhile
            base.localize(frames[block[0]].image_path, cams[block[0]])
        return [1000 * base.localize(frames[i].image_path, cams[i]).seconds for i in block]

    for f, c, p in zip(frames, cams, priors):  # fills the voxel cache
        loc.localize(f.image_path, p, c)
    base.localize(frames[0].image_path, cams[0])
    warm, warm_base = [], []
    for block in blocks:
        rows = []
        for i in block:
            s = time.perf_counter()
            res = loc.localize(frames[i].image_path, priors[i], cams[i])
            rows.append(row(res, time.perf_counter() - s))
        warm.append(rows)
        warm_base.append(baseline_block(block))
    stream, stream_base = [], []
    frames_of = loc.localize_sequence([f.image_path for f in frames], priors[0], cams[0])
    for k, block in enumerate(blocks):
        rows, s = [], time.perf_counter()
        for j in range(len(block)):
            res = next(frames_of)
            now = time.perf_counter()
            # a later block's first frame was extracted during the baseline's block: counted, not timed
            rows.append(row(res, np.nan if k and j == 0 else now - s))
            s = now
        stream.append(rows)
        stream_base.append(baseline_block(block, untimed_first=True))
    frames_of.close()
    b = float(np.median(np.concatenate(warm_base + stream_base)))
    built = "reused" if build_s is None else f"built in {build_s:.0f} s"
    print(
        f"{sp.name}: map {path.name} ({len(m):,} landmarks, {built}"
        f", voxel cache {m.cache_bytes / 2**20:.0f} MB; a warm localizer's process {warm_memory(args, path)})"
        f", {len(frames)} queries; baseline {len(base.points3d):,} "
        f"points (built in {base_build:.0f} s); device {args.device}, localizer threads {args.threads}"
        f", load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"median ms per query; favormap and the baseline take turns in blocks of {BLOCK} queries, each mode's "
        "ratio is to the baseline's queries of its own turns (a stream's first frame after a baseline block is "
        "not timed: it was extracted meanwhile)\n"
    )
    print("| mode | " + " | ".join(stages) + " | total | x baseline | blocks: x baseline | localized |")
    print("|---" * (len(stages) + 5) + "|")
    for name, runs, base_ms in (("warm (nearest frame)", warm, warm_base), ("stream", stream, stream_base)):
        r = np.array([x for rows in runs for x in rows], np.float64)
        timed = r[np.isfinite(r[:, len(stages)])]
        med = np.median(timed[:, : len(stages) + 1], axis=0)
        walls = [np.array(rows, np.float64)[:, len(stages)] for rows in runs]
        per_block = [np.nanmedian(w) / np.median(bb) for w, bb in zip(walls, base_ms) if np.isfinite(w).any()]
        print(
            f"| {name} | "
            + " | ".join(f"{v:.0f}" for v in med[: len(stages)])
            + f" | {med[-1]:.0f} | {med[-1] / np.median(np.concatenate(base_ms)):.2f}"
            + f" | {np.median(per_block):.2f} ({min(per_block):.2f}-{max(per_block):.2f})"
            + f" | {int(r[:, -1].sum())}/{len(r)} |"
        )
    print("| pycolmap-SIFT baseline | " + " | ".join("-" for _ in stages) + f" | {b:.0f} | 1.00 | - | - |")
    m.close()
    return 0


def localize_threads(args):
    """``--threads`` as LocalizeConfig.threads."""
    t = args.threads.lower()
    return None if t == "none" else ("auto" if t == "auto" else int(t))


def warm_memory(args, path) -> str:
    """Memory of a warm localizer of map ``path``, measured in a fresh process that imports only what
    localizing needs: the split's queries localized twice from the nearest mapping frame."""
    out = subprocess.run(
        [sys.executable, __file__, "--split", args.split, "--memory-of", str(path), "--device", args.device]
        + ["--threads", args.threads],
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        return "memory not measured"
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return f"{r['rss_mb']:.0f} MB resident, peak {r['peak_mb']:.0f} MB{', torch imported' if r['torch'] else ''}"


def memory_child(args) -> dict:
    """``--memory-of MAP``: localize the split's queries twice with one Localizer; the process's memory."""
    from accuracy.splits import real_splits

    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.evaluate import EvalConfig, make_priors
    from favormap.mapfile import Map

    sp = real_splits([args.split])[0]
    m = Map.open(args.memory_of)
    loc = Localizer(m, LocalizeConfig(device=args.device, threads=localize_threads(args)))
    priors = make_priors(sp.queries, m.rig_from_world, EvalConfig(prior_mode="nearest"))
    for _ in range(2):
        for f, p in zip(sp.queries.frames, priors):
            loc.localize(f.image_path, p, sp.queries.cameras[f.camera_id])
    return {"rss_mb": rss_mb(), "peak_mb": peak_rss_mb(), "torch": "torch" in sys.modules}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", help="a real split of tools/bench_accuracy.py (e.g. tum-desk-xyz) instead of the room")
    ap.add_argument("--refine-poses", action="store_true", help="--split: the map built with --refine-poses")
    ap.add_argument("--workdir", default="/tmp/favormap-bench-accuracy", help="--split: where its maps are kept")
    ap.add_argument("--map")
    ap.add_argument("--queries", type=int, default=10)
    ap.add_argument(
        "--passes",
        type=int,
        default=3,
        help="localize the queries this many times (same priors); ms/query is the median pass's mean",
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--threads",
        default="auto",
        help="LocalizeConfig.threads: auto (as the CLI), a count, or none (the pools left alone, as a Python "
        "program that does not ask)",
    )
    ap.add_argument("--descriptors", default="rendered")
    ap.add_argument("--large", type=int, default=1_000_000, help="landmarks of the large map (0: no large map)")
    ap.add_argument("--large-map", help="file for the large map (kept; reused when it exists)")
    ap.add_argument("--measure", help=argparse.SUPPRESS)  # child process: measure this map
    ap.add_argument("--sequence", help=argparse.SUPPRESS)
    ap.add_argument("--memory-of", help=argparse.SUPPRESS)  # child process: a warm localizer's memory
    args = ap.parse_args()
    if args.memory_of:
        print(json.dumps(memory_child(args)))
        return 0
    if args.measure:
        print(json.dumps(measure(args)))
        return 0
    if args.split:
        return real_split_timing(args)

    from favormap.build import BuildConfig, build_map
    from favormap.mapfile import write_map
    from favormap.synthetic import write_sequence

    tmp = tempfile.TemporaryDirectory()
    seq_dir = Path(tmp.name) / "room"
    seq = write_sequence(seq_dir, n_frames=30, width=640, height=480)
    path = args.map
    if path is None:
        path = Path(tmp.name) / "room.h5"
        t = time.perf_counter()
        write_map(build_map(seq, BuildConfig(max_landmarks=1500), device=args.device), path)
        print(f"built map in {time.perf_counter() - t:.1f} s")
    maps = [Path(path)]
    if args.large:
        big = Path(args.large_map) if args.large_map else Path(tmp.name) / "large.h5"
        if not big.exists():
            info = write_tiled(Path(path), big, args.large)
            print(
                f"wrote {big}: {info['landmarks']:,} landmarks ({info['copies']} copies of the map, "
                f"{info['spacing']:.1f} units apart), {info['file_gb']:.2f} GB in {info['write_s']:.0f} s"
            )
        maps.append(big)

    results = []
    for p in maps:
        cmd = [
            sys.executable,
            __file__,
            "--measure",
            str(p),
            "--sequence",
            str(seq_dir),
            "--queries",
            str(args.queries),
            "--passes",
            str(args.passes),
            "--device",
            args.device,
            "--descriptors",
            args.descriptors,
            "--threads",
            args.threads,
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "RERUN_ANALYTICS": "false"})
        if out.returncode:
            sys.stderr.write(out.stderr)
            return 1
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))

    r0 = results[0]
    print(
        f"{args.queries} queries 640x480 x {args.passes} passes, up to 3 iterations, device {args.device}, "
        f"descriptors {args.descriptors}; "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    stages = list(r0["stages_ms"])
    print(
        f"{'landmarks':>10} {'open s':>7}"
        + "".join(f"{s:>11}" for s in stages)
        + f"{'ms/query':>10}{'x room':>8}{'peak RSS MB':>13}{'x room':>8}"
        + f"{'voxel KB/q':>11}{'localized':>10}{'median err':>18}{'iters':>7}{'guided':>7}"
    )
    for r in results:
        print(
            f"{r['landmarks']:>10,} {r['open_s']:>7.2f}"
            + "".join(f"{r['stages_ms'][s]:>11.1f}" for s in stages)
            + f"{r['total_ms']:>10.1f}{r['total_ms'] / r0['total_ms']:>8.2f}{r['peak_rss_mb']:>13.0f}"
            f"{r['peak_rss_mb'] / r0['peak_rss_mb']:>8.2f}{r['voxel_kb_per_query']:>11.0f}"
            f"{r['localized']:>5}/{r['queries']:<4}{r['median_error'][0]:>9.4f} / {r['median_error'][1]:.3f}°"
            f"{r['render_iterations']:>7.1f}{r['guided']:>7}"
        )
        print(f"  {Path(r['map']).name}: ms/query of each pass " + ", ".join(f"{v:.1f}" for v in r["pass_ms"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
