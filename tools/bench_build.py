#!/usr/bin/env python3
"""Per-stage build times on a sequence (default: ../shared/data/fox, else a synthetic room).

python tools/bench_build.py [SEQ] [--max-landmarks 1500] [--workers N] [--device cuda [--patches-on cpu]]
python tools/bench_build.py [SEQ] --repeat 5    # five builds, each in a fresh process: every run and the median

This machine's speed moves by 10-15 % within minutes: compare medians of several runs, or alternate
two versions run by run (``PYTHONPATH=WORKTREE python WORKTREE/tools/bench_build.py SEQ``).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", default=None)
    ap.add_argument("--max-landmarks", type=int, default=None, help="default: the build default")
    ap.add_argument("--min-track", type=int, default=None, help="default: the build default")
    ap.add_argument("--match-window", type=int, default=None, help="tracking window (default: the build default)")
    ap.add_argument(
        "--max-epipolar", type=float, default=None, help="tracking epipolar px (default: the build default)"
    )
    ap.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="Adam iterations (--quality fast / reference; the closed-form presets have none)",
    )
    ap.add_argument("--extractor", default=None, help="default: the build default")
    ap.add_argument(
        "--exact-patches", action="store_true", help="describe every patch pixel (favormap build --exact-patches)"
    )
    ap.add_argument("--quality", default=None, help="voxel training preset (quick | balanced | fast | reference)")
    ap.add_argument(
        "--max-side", type=int, default=None, help="working resolution (0: full size; default: the build default)"
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument(
        "--workers", type=int, default=None, help="threads for the CPU stages (default: the thread rule; 1: serial)"
    )
    ap.add_argument(
        "--patches-on",
        choices=("auto", "cpu"),
        default="auto",
        help="auto: SIFT's patch descriptors on the GPU when --device is one (favormap.features.sift_torch); "
        "cpu: OpenCV on the CPU threads whatever the device (the build before sift_torch, for comparison)",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run the benchmark N times, each in a fresh process (as a `favormap build` would), and print "
        "every run's stages and their medians",
    )
    args = ap.parse_args()
    if args.repeat > 1:
        return repeat(args.repeat)

    from favormap.build import BuildConfig, build_map
    from favormap.executor import LocalExecutor
    from favormap.io import read_sequence
    from favormap.mapfile import write_map

    tmp = tempfile.TemporaryDirectory()
    seq_path = args.sequence
    if seq_path is None:
        fox = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fox"
        if fox.is_dir():
            seq_path = str(fox)
        else:
            from favormap.synthetic import write_sequence

            seq_path = str(Path(tmp.name) / "room")
            write_sequence(seq_path, n_frames=30)
    seq = read_sequence(seq_path)
    cfg = BuildConfig(**({"extractor": args.extractor} if args.extractor else {}))  # its default voxel preset
    for k, field in (
        ("max_landmarks", "max_landmarks"),
        ("min_track", "min_track"),
        ("match_window", "match_window"),
        ("max_epipolar", "max_epipolar_px"),
    ):
        if getattr(args, k) is not None:
            setattr(cfg, field, getattr(args, k))
    if args.max_side is not None:
        cfg.max_side = args.max_side
    if args.quality:
        from favormap.voxels import VoxelConfig

        cfg.voxel = VoxelConfig.preset(args.quality)
    if args.iterations:
        cfg.voxel.iterations = args.iterations
    if args.exact_patches:
        cfg.voxel.patch_interp = False
    if args.patches_on == "cpu":
        import favormap.build as fb

        fb.ExtractorSpec.samples_on_device = property(lambda self: False)
    t = time.perf_counter()
    with LocalExecutor(args.device, workers=args.workers) as ex:
        m = build_map(seq, cfg, executor=ex)
    out = Path(tmp.name) / "bench.h5"
    tw = time.perf_counter()
    write_map(m, out)
    write_s = time.perf_counter() - tw
    total = time.perf_counter() - t
    timings = dict(m.provenance["timings"], write=round(write_s, 3))
    st = m.provenance["stats"]
    print(
        f"sequence {seq_path}: {len(seq)} frames, {st['landmarks']} landmarks, extractor {cfg.extractor}, "
        f"quality {args.quality or 'default'}, match window {cfg.match_window}, "
        f"epipolar {st['max_epipolar_px']:.2f} px, max side {cfg.max_side}, device {args.device}, "
        f"patches on {'cpu' if args.patches_on == 'cpu' or args.device == 'cpu' else args.device}, "
        f"CPU-stage workers {m.provenance['executor']['workers']}, torch threads {torch.get_num_threads()}, "
        f"cores {os.cpu_count()}"
    )
    print(f"{'stage':<12} {'seconds':>9} {'share':>7}")
    for k, v in timings.items():
        print(f"{k:<12} {v:>9.2f} {100 * v / total:>6.1f}%")
    print(f"{'total':<12} {total:>9.2f}")
    print(
        f"median reproj {st['median_reproj_error_px']:.3f} px, median PSNR {st['median_psnr']:.2f} dB, "
        f"file {out.stat().st_size / 1e6:.1f} MB"
    )


def repeat(n: int) -> int:
    """This script ``n`` times in fresh processes (its other arguments unchanged): each run's stage
    seconds, then the median of each stage."""
    import statistics
    import subprocess

    argv = [*sys.argv[1:], "--repeat", "1"]  # the other arguments unchanged; argparse takes the last --repeat
    runs: list[dict[str, float]] = []
    for k in range(n):
        out = subprocess.run([sys.executable, __file__, *argv], capture_output=True, text=True)
        if out.returncode:
            sys.stderr.write(out.stdout + out.stderr)
            return out.returncode
        lines = out.stdout.splitlines()
        if k == 0:
            print(lines[0])
        stages = {}
        for ln in lines:
            parts = ln.split()
            if len(parts) >= 2 and parts[0] != "stage" and _number(parts[1]):
                stages[parts[0]] = float(parts[1])
        runs.append(stages)
        print(f"run {k + 1}: " + "  ".join(f"{s} {v:.2f}" for s, v in stages.items()), flush=True)
    names = list(runs[0])
    print(f"{'stage':<12} {'median':>8} {'min':>8} {'max':>8}   ({n} runs)")
    for s in names:
        v = [r[s] for r in runs if s in r]
        print(f"{s:<12} {statistics.median(v):>8.2f} {min(v):>8.2f} {max(v):>8.2f}")
    return 0


def _number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


if __name__ == "__main__":
    sys.exit(main())
