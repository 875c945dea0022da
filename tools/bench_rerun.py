#!/usr/bin/env python
"""Overhead of rerun logging on `favormap build` (target: <= 10 %).

Renders a synthetic sequence (default 24 frames, 640x480), then runs `favormap build` on it with
and without `--rerun-save`, interleaved (plain, rerun, rerun, plain, ...) so that a drift in machine
load affects both alike, each run in a fresh process (so importing rerun is part of the cost).
Reports wall time and CPU time (user + system of the child; far less sensitive than wall time
to other processes on a shared machine) and the overhead of the medians.

    python tools/bench_rerun.py                       # 24 frames 640x480, 1500 landmarks, 3 pairs
    python tools/bench_rerun.py --repeats 5 --iterations 200 --keep /tmp/bench
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_build(seq: Path, out: Path, rrd: Path | None, args) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "favormap",
        "build",
        str(seq),
        "-o",
        str(out),
        "--max-landmarks",
        str(args.max_landmarks),
        "--resize",
        str(args.resize),
        "--iterations",
        str(args.iterations),
        "--device",
        "cpu",
        "-q",
        "--json",
    ]
    if rrd is not None:
        cmd += ["--rerun-save", str(rrd)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "CI": "1"})
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit(f"build failed ({p.returncode}): {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ''}")
    s = json.loads(p.stdout.strip().splitlines()[-1])
    return {
        "wall": wall,
        "cpu": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "stages": s["total_seconds"],
        "landmarks": s["landmarks"],
        "rrd_mb": rrd.stat().st_size / 2**20 if rrd is not None else 0.0,
    }


def hook_seconds(seq: Path, rrd: Path, args) -> tuple[float, float]:
    """In-process build with the recorder's hooks timed: (seconds spent logging, including importing
    rerun, opening and closing the recording; total seconds). Insensitive to machine load."""
    from favormap.build import BuildConfig, BuildObserver, build_map
    from favormap.io import read_sequence
    from favormap.voxels import VoxelConfig

    spent = [0.0]

    def timed(fn):
        def wrapper(*a, **kw):
            t = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                spent[0] += time.perf_counter() - t

        return wrapper

    cfg = BuildConfig(
        max_side=args.resize,
        max_landmarks=args.max_landmarks,
        voxel=VoxelConfig(iterations=args.iterations),
    )
    seq_ = read_sequence(seq)
    t0 = time.perf_counter()
    rec = timed(
        lambda: __import__("favormap.viz.recording", fromlist=["Recording"]).Recording(
            "favormap build", kind="build", save=rrd
        )
    )()
    inner = rec.build_observer()

    class Timed(BuildObserver):
        wants_images = inner.wants_images

    for name in ("on_frames", "on_tracks", "on_landmarks", "on_train_step", "on_map"):
        setattr(Timed, name, staticmethod(timed(getattr(inner, name))))
    build_map(seq_, cfg, observer=Timed())
    timed(rec.close)()
    return spent[0], time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--max-landmarks", type=int, default=1500)
    ap.add_argument("--iterations", type=int, default=200, help="voxel training iterations (build default 200)")
    ap.add_argument("--resize", type=int, default=640)
    ap.add_argument("--repeats", type=int, default=3, help="pairs of runs (default 3)")
    ap.add_argument("--no-hooks", action="store_true", help="skip the in-process measurement of the logging hooks")
    ap.add_argument("--keep", metavar="DIR", help="work in DIR and keep the sequence, maps and recording")
    args = ap.parse_args(argv)

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="favormap_bench_rerun_"))
    work.mkdir(parents=True, exist_ok=True)
    seq = work / "seq"
    if not (seq / "sequence.json").exists():
        from favormap.synthetic import write_sequence

        t = time.perf_counter()
        write_sequence(seq, n_frames=args.frames, width=args.width, height=args.height)
        print(f"rendered {args.frames} frames {args.width}x{args.height} in {time.perf_counter() - t:.1f} s -> {seq}")
    run_build(seq, work / "warmup.h5", None, args)  # warm the file cache and the Python bytecode
    rows = []
    for r in range(args.repeats):
        order = [False, True] if r % 2 == 0 else [True, False]
        for with_rerun in order:
            res = run_build(seq, work / "map.h5", work / "build.rrd" if with_rerun else None, args)
            rows.append({"run": r + 1, "rerun": with_rerun, **res})
            print(
                f"  run {r + 1} {'--rerun-save' if with_rerun else 'plain       '}  wall {res['wall']:7.2f} s  "
                f"cpu {res['cpu']:7.2f} s  stages {res['stages']:7.2f} s",
                flush=True,
            )

    def med(key, flag):
        return statistics.median(x[key] for x in rows if x["rerun"] == flag)

    print()
    print(
        f"favormap build, {args.frames} frames {args.width}x{args.height}, --max-landmarks {args.max_landmarks}, "
        f"--iterations {args.iterations}, {rows[0]['landmarks']} landmarks, median of {args.repeats}"
    )
    print(f"{'':24}{'plain':>10}{'--rerun-save':>14}{'overhead':>11}")
    for key, label in (("wall", "wall time (s)"), ("cpu", "CPU time (s)"), ("stages", "sum of stages (s)")):
        a, b = med(key, False), med(key, True)
        print(f"{label:24}{a:10.2f}{b:14.2f}{100 * (b - a) / a:10.1f} %")
    print(f"{'recording size (MB)':24}{'':10}{med('rrd_mb', True):14.2f}")
    if not args.no_hooks:
        spent, total = hook_seconds(seq, work / "hooks.rrd", args)
        print(
            f"time inside the rerun hooks (in-process build, incl. importing rerun and closing the file): "
            f"{spent:.2f} s of {total:.2f} s = {100 * spent / total:.1f} %"
        )
    if not args.keep:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
