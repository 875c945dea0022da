#!/usr/bin/env python3
"""Voxel training alone: time per iteration on a device, and where it goes (torch profiler).

The training rays of a sequence are made once (extract, track, triangulate, patches: the build's
own stages with the build defaults) and kept in ``--rays FILE`` (.npz) for later runs; then every
landmark is trained ``--repeat`` times with the build's batching, the first run counted as warm-up
on a GPU. ``--profile`` prints the torch profiler's table of the last run (top operators by device
time, or CPU time on a CPU).

    python tools/bench_train.py [SEQ] [--device cuda] [--extractor disk] [--max-side 640] [--quality fast] [--profile]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch


def training_data(seq_path: str, cfg, device: str):
    from favormap.build import (
        ExtractorSpec,
        extract_sequence,
        select_landmarks,
        track_frames,
        training_rays,
        triangulate_tracks,
    )
    from favormap.executor import LocalExecutor
    from favormap.io import read_sequence

    seq = read_sequence(seq_path)
    spec = ExtractorSpec(cfg.extractor, cfg.max_keypoints)
    with LocalExecutor(device) as ex:
        ff = extract_sequence(seq, spec, cfg.max_side, executor=ex)
        lms = select_landmarks(triangulate_tracks(track_frames(ff, cfg), ff, cfg), cfg.max_landmarks)
        return training_rays(
            lms,
            ff,
            spec,
            cfg.voxel.patch_size,
            cfg.voxel.box_factor,
            ex,
            patch_stride=cfg.voxel.patch_stride,
            patch_interp=cfg.voxel.patch_interp,
        )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", default=None, help="default: ../shared/data/fox")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--extractor", default=None, help="feature extractor (default: the build's, SIFT)")
    ap.add_argument("--max-side", type=int, default=None, help="working resolution (0: full size)")
    ap.add_argument("--quality", default=None, help="voxel preset (default: the build's)")
    ap.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="Adam iterations (--quality fast / reference; the closed-form presets have none)",
    )
    ap.add_argument("--samples", type=int, default=None, help="samples per ray (default: the preset's)")
    ap.add_argument("--rays", default=None, help="cache of the training rays (.npz): read if it exists, else written")
    ap.add_argument("--batch", type=int, default=None, help="landmarks per training batch (default: the build's)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()

    from dataclasses import asdict, fields

    from favormap.build import BuildConfig, train_batches
    from favormap.executor import LocalExecutor
    from favormap.threads import configure_threads
    from favormap.voxels import VoxelConfig
    from favormap.voxels.config import TrainingRays, voxel_config_for

    configure_threads()
    cfg = BuildConfig(**({"extractor": args.extractor} if args.extractor else {}))  # the extractor's defaults
    if args.max_side is not None:
        cfg.max_side = args.max_side
    if args.quality:
        cfg.voxel = VoxelConfig.preset(args.quality)
    if args.iterations:
        cfg.voxel.iterations = args.iterations
    if args.samples:
        cfg.voxel.samples = args.samples
    if args.batch:
        cfg.train_batch = args.batch
    cfg.voxel = voxel_config_for(cfg.voxel, cfg.extractor)  # as build_map resolves it
    seq_path = args.sequence or str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fox")
    t = time.perf_counter()
    if args.rays and Path(args.rays).exists():
        with np.load(args.rays) as z:
            rays = TrainingRays(**{f.name: z[f.name] for f in fields(TrainingRays) if f.name in z})
        made = "read from " + args.rays
    else:
        rays = training_data(seq_path, cfg, args.device)
        if args.rays:
            np.savez(args.rays, **{k: v for k, v in asdict(rays).items() if v is not None})
        made = f"made in {time.perf_counter() - t:.1f} s"
    L, O = len(rays.centers), len(rays.obs_landmark)
    print(
        f"{seq_path}: {L} landmarks, {O} observations, {rays.targets.shape[1]} pixels x {rays.targets.shape[2]} "
        f"channels per patch ({made}); quality {args.quality or 'default'} ({cfg.voxel.solver}), "
        f"{cfg.voxel.iterations} iterations, "
        f"{cfg.voxel.samples} samples per ray, "
        f"batches of {cfg.train_batch}, device {args.device}, torch threads {torch.get_num_threads()}"
    )
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    times = []
    with LocalExecutor(args.device) as ex:
        for r in range(args.repeat):
            last = r == args.repeat - 1
            prof = None
            if last and args.profile:
                acts = [torch.profiler.ProfilerActivity.CPU]
                if args.device.startswith("cuda"):
                    acts.append(torch.profiler.ProfilerActivity.CUDA)
                prof = torch.profiler.profile(activities=acts)
                prof.__enter__()
            sync()
            t = time.perf_counter()
            grids = train_batches(rays, cfg.voxel, cfg.train_batch, ex)
            sync()
            times.append(time.perf_counter() - t)
            if prof is not None:
                prof.__exit__(None, None, None)
            print(
                f"run {r + 1}: {times[-1]:.2f} s, {1e3 * times[-1] / cfg.voxel.iterations:.1f} ms per iteration "
                f"(total / iterations), "
                f"median PSNR {float(np.median(grids.psnr)):.2f} dB"
            )
    if prof is not None:
        key = "self_cuda_time_total" if args.device.startswith("cuda") else "self_cpu_time_total"
        print(prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=60))
    return 0


if __name__ == "__main__":
    sys.exit(main())
