#!/usr/bin/env python3
"""Peak memory of a build against the number of frames (issue: bounded-memory builds).

    python tools/bench_build_memory.py [--frames 100,1000,5000] [--modes stream,memory]
                                       [--workdir DIR] [--quality quick]

Renders a synthetic room sequence of the largest frame count once (320x240, kept in ``--workdir``
and reused), then builds a map from its first N frames for each N, each build in a fresh process,
and prints one row per (N, mode): the build's peak resident memory (VmHWM of that process), its
time, the landmarks and the size of the feature cache. Modes: ``stream`` (features in an on-disk
feature cache, build_map(feature_cache=FILE)) and ``memory`` (every frame's features in RAM, the
way short sequences are built). Target: a 5,000-frame build peaks at <= 4 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(args) -> None:
    """One build in this (fresh) process; prints a JSON line."""
    sys.path.insert(0, str(ROOT / "tools"))
    from bench_ops import peak_rss_mb

    from favormap.build import BuildConfig, build_map
    from favormap.io import read_sequence
    from favormap.voxels import VoxelConfig

    seq = read_sequence(args.sequence)
    seq = seq.subset(list(range(args.n)))
    cfg = BuildConfig(max_side=0, voxel=VoxelConfig.preset(args.quality))
    cache = None
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="favormap-bench-mem-", dir=args.workdir) as tmp:
        if args.mode == "stream":
            cache = Path(tmp) / "features.h5"
        m = build_map(seq, cfg, feature_cache=cache if cache else False)
        cache_mb = cache.stat().st_size / 2**20 if cache else 0.0
    print(
        json.dumps(
            {
                "frames": args.n,
                "mode": args.mode,
                "peak_rss_mb": round(peak_rss_mb(), 1),
                "seconds": round(time.perf_counter() - t, 1),
                "landmarks": m.provenance["stats"]["landmarks"],
                "cache_mb": round(cache_mb, 1),
                "timings": m.provenance["timings"],
            }
        )
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", default="100,1000,5000")
    ap.add_argument("--modes", default="stream,memory")
    ap.add_argument("--workdir", default=None, help="keeps the rendered sequence (default: a temporary folder)")
    ap.add_argument("--quality", default="quick", help="voxel preset of the builds (default quick)")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--sequence", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mode", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)

    frames = sorted(int(x) for x in args.frames.split(","))
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="favormap-bench-mem-")
        args.workdir = tmp.name
    work = Path(args.workdir)
    seq_dir = work / f"room-{frames[-1]}"
    if not (seq_dir / "sequence.json").exists():
        from favormap.synthetic import write_sequence

        t = time.perf_counter()
        write_sequence(seq_dir, n_frames=frames[-1], width=320, height=240, ss=1)
        print(f"rendered {frames[-1]} frames (320x240) in {time.perf_counter() - t:.0f} s", flush=True)
    rows = []
    print(f"{'frames':>7} {'mode':<7} {'peak RSS MB':>12} {'seconds':>8} {'landmarks':>9} {'cache MB':>9}  stages (s)")
    for n in frames:
        for mode in args.modes.split(","):
            cmd = [sys.executable, __file__, "--child", "--sequence", str(seq_dir), "--n", str(n), "--mode", mode]
            cmd += ["--quality", args.quality, "--workdir", str(work)]
            r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
            if r.returncode != 0:
                print(f"{n:>7} {mode:<7} failed: {r.stderr.strip().splitlines()[-1:]}", flush=True)
                continue
            row = json.loads(r.stdout.strip().splitlines()[-1])
            rows.append(row)
            stages = ", ".join(f"{k} {v:.0f}" for k, v in row["timings"].items())
            print(
                f"{n:>7} {mode:<7} {row['peak_rss_mb']:>12.0f} {row['seconds']:>8.0f} {row['landmarks']:>9} "
                f"{row['cache_mb']:>9.0f}  {stages}",
                flush=True,
            )
    print(f"(machine: {os.cpu_count()} cores; peak RSS = VmHWM of the build's own process)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
