#!/usr/bin/env python3
"""SIFT's patch descriptors (a build's "patches" stage) by OpenCV on the CPU threads against
favormap.features.sift_torch on a device: time per frame, the pyramid's share, and agreement.

python tools/bench_patches.py [SEQ] [--max-side 640] [--device cuda] [--frames 40] [--obs 240] [--profile]
                              [--budgets 4194304,67108864]

Each frame gets ``--obs`` observations (random keypoints; the fox build has ~240 per frame) with a
7 x 7 patch around each, as the build samples them.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", default=None)
    ap.add_argument("--max-side", type=int, default=640, help="working resolution (0: full size)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--obs", type=int, default=240, help="observations per frame")
    ap.add_argument("--patch", type=int, default=7)
    ap.add_argument("--profile", action="store_true", help="torch profiler: the kernels that take the time")
    ap.add_argument(
        "--budgets",
        default="",
        help="also time the device with these chunk sizes (window pixels per chunk, comma-separated) instead of "
        "sift_torch's default (GPU: 2^24, at most a quarter of the free memory at ~400 bytes each)",
    )
    args = ap.parse_args()

    from favormap import features
    from favormap.features import sift_torch
    from favormap.features.base import patch_offsets
    from favormap.io import read_sequence
    from favormap.io.images import load_image
    from favormap.threads import configure_threads, serial_pools

    seq_path = args.sequence or str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fox")
    seq = read_sequence(seq_path)
    frames = seq.frames[: args.frames]
    ex = features.create("sift")
    rng = np.random.default_rng(0)
    feats, pts = [], []
    for fr in frames:
        f = ex.extract(load_image(fr.image_path, seq.cameras[fr.camera_id], args.max_side)[0])
        kp = f.keypoints[rng.choice(len(f), min(args.obs, len(f)), replace=False)]
        feats.append(f)
        pts.append((kp[:, None] + patch_offsets(args.patch)[None]).reshape(-1, 2).astype(np.float32))
    n_pts = sum(len(p) for p in pts)
    workers = configure_threads()
    cpu_ex = [features.create("sift") for _ in range(workers)]

    t = time.perf_counter()
    with serial_pools(), ThreadPoolExecutor(workers) as pool:
        ref = list(pool.map(lambda i: cpu_ex[i % workers].sample(feats[i], pts[i]), range(len(frames))))
    t_cpu = time.perf_counter() - t

    dev = features.create("sift", device=args.device, torch_descriptors=True)
    sync = torch.cuda.synchronize if str(args.device).startswith("cuda") else (lambda: None)
    t = time.perf_counter()
    dev.sample(feats[0], pts[0][:10])  # the device's start-up (CUDA context, kernels)
    sync()
    t_init = time.perf_counter() - t
    t = time.perf_counter()
    for f in feats:
        sift_torch.gaussian_pyramid(torch.as_tensor(f.dense.gray, device=args.device), 6)
    sync()
    t_pyr = time.perf_counter() - t
    t = time.perf_counter()
    out = [dev.sample(f, p) for f, p in zip(feats, pts)]
    sync()
    t_dev = time.perf_counter() - t
    cos = np.concatenate([np.sum(a * b, axis=1) for a, b in zip(out, ref)])
    t_budget = {}
    for b in [int(v) for v in args.budgets.split(",") if v.strip()]:
        default_budget = sift_torch._default_budget
        sift_torch._default_budget = lambda device, b=b: b  # a benchmark's override, not a build option
        try:
            t = time.perf_counter()
            same = all(np.array_equal(dev.sample(f, p), o) for f, p, o in zip(feats, pts, out))
            sync()
            t_budget[b] = (time.perf_counter() - t, same)
        finally:
            sift_torch._default_budget = default_budget

    h, w = feats[0].dense.gray.shape
    print(
        f"sequence {seq_path}: {len(frames)} frames of {w} x {h}, {n_pts} points ({args.obs} observations x "
        f"{args.patch}^2 per frame), cores {os.cpu_count()}, device {args.device}"
    )
    print(f"{'what':<44} {'seconds':>8} {'us/point':>9}")
    print(f"{f'OpenCV, {workers} threads':<44} {t_cpu:>8.2f} {1e6 * t_cpu / n_pts:>9.2f}")
    print(f"{f'torch on {args.device}: start-up (once per process)':<44} {t_init:>8.2f}")
    print(f"{f'torch on {args.device}: pyramids alone (octaves -1..6)':<44} {t_pyr:>8.2f}")
    print(f"{f'torch on {args.device}: sample (pyramid + descriptors)':<44} {t_dev:>8.2f} {1e6 * t_dev / n_pts:>9.2f}")
    for b, (sec, same) in t_budget.items():
        label = f"torch on {args.device}: sample, chunks of {b} px"
        print(f"{label:<44} {sec:>8.2f} {1e6 * sec / n_pts:>9.2f}  ({'same' if same else 'OTHER'} descriptors)")
    print(
        f"cosine to OpenCV's: min {cos.min():.6f}, median {np.median(cos):.7f}, exact {np.mean(cos >= 0.9999995):.3f}"
    )
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
        with profile(activities=acts) as prof:
            for f, p in zip(feats[:8], pts[:8]):
                dev.sample(f, p)
            sync()
        key = "self_cuda_time_total" if torch.cuda.is_available() else "self_cpu_time_total"
        print(prof.key_averages().table(sort_by=key, row_limit=18))


if __name__ == "__main__":
    main()
