#!/usr/bin/env python3
"""Build scaling on a local Ray instance with 1, 2, 4, ... worker CPUs (favormap build --ray).

    python tools/bench_distributed.py [--workers 1,2,4] [--frames 30] [--max-landmarks 1500]
                                      [--train-batch 256] [--iterations 200] [--sequence SEQ]

Builds the same map single-process (LocalExecutor) and on a local Ray instance started with
``num_cpus = N`` for each N (one CPU per task, so N tasks run at a time), prints the seconds per
stage, the speed-up of the parallel stages against N = 1, the driver's share (tracking +
triangulation, which stay on the driver) and the worst per-landmark descriptor cosine against the
single-process map. Ray's start-up is timed apart (not part of the build). On a machine with fewer
cores than N the extra workers only share the cores: run it where the cores exist.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PARALLEL = ("extract", "patches", "train")
DRIVER = ("track", "triangulate")


def min_cosine(a, b) -> float:
    L, C = len(a.positions), a.channels
    da, db = a.descriptors.reshape(L, -1, C).astype(np.float64), b.descriptors.reshape(L, -1, C).astype(np.float64)
    cos = (da * db).sum(-1) / np.maximum(np.linalg.norm(da, axis=-1) * np.linalg.norm(db, axis=-1), 1e-12)
    return float(cos.min())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", default="1,2,4", help="comma-separated worker CPU counts (default 1,2,4)")
    ap.add_argument("--sequence", help="a sequence to build (default: a synthetic 640x480 room)")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--max-landmarks", type=int, default=1500)
    ap.add_argument("--train-batch", type=int, default=256)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--no-local", action="store_true", help="skip the single-process build")
    args = ap.parse_args()
    workers = [int(w) for w in args.workers.split(",")]

    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    from favormap.build import BuildConfig, build_map
    from favormap.distributed import RayExecutor
    from favormap.io import read_sequence
    from favormap.synthetic import write_sequence

    tmp = tempfile.TemporaryDirectory()
    if args.sequence:
        seq = read_sequence(args.sequence)
    else:
        seq = write_sequence(Path(tmp.name) / "room", n_frames=args.frames, width=640, height=480)
    cfg = BuildConfig(max_landmarks=args.max_landmarks, train_batch=args.train_batch)
    cfg.voxel.iterations = args.iterations

    runs = []  # (label, timings, total, map, startup)
    if not args.no_local:
        t = time.perf_counter()
        m = build_map(seq, cfg)
        runs.append(("local", m.provenance["timings"], time.perf_counter() - t, m, 0.0))
    for n in workers:
        t = time.perf_counter()
        ex = RayExecutor("local", num_cpus=n)
        startup = time.perf_counter() - t
        with ex:
            t = time.perf_counter()
            m = build_map(seq, cfg, executor=ex)
            runs.append((f"ray {n} cpu", m.provenance["timings"], time.perf_counter() - t, m, startup))

    ref = runs[0][3]
    print(
        f"sequence: {len(seq)} frames, {len(ref.positions)} landmarks, {args.iterations} iterations, train batch "
        f"{args.train_batch} ({-(-len(ref.positions) // args.train_batch)} tasks); machine: {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f} at the end"
    )
    stages = list(runs[0][1])
    head = (
        f"{'run':<10}"
        + "".join(f"{s:>12}" for s in stages)
        + f"{'total':>9}{'parallel x':>11}{'driver':>8}{'ray start':>10}{'min cos':>9}"
    )
    print(head)
    base = None
    for label, tm, total, m, startup in runs:
        par = sum(tm.get(s, 0) for s in PARALLEL)
        if label.startswith("ray") and base is None:
            base = par
        speed = f"{base / par:>10.2f}x" if label.startswith("ray") and base else f"{'':>11}"
        drv = sum(tm.get(s, 0) for s in DRIVER) / total
        same = len(m.positions) == len(ref.positions) and np.allclose(m.positions, ref.positions)
        cos = f"{min_cosine(ref, m):>9.5f}" if same else f"{'differs':>9}"
        print(
            f"{label:<10}"
            + "".join(f"{tm.get(s, 0):>12.2f}" for s in stages)
            + f"{total:>9.2f}{speed}{100 * drv:>7.1f}%"
            f"{startup:>10.1f}{cos}"
        )
    print(
        "parallel x: extract + patches + train of the first Ray run / this run's; driver: track + triangulate / total"
    )


if __name__ == "__main__":
    sys.exit(main())
