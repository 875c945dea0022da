#!/usr/bin/env python3
"""DISK extraction: the network's full forward pass against favormap's, which evaluates the last
convolution's 128 descriptor channels only where descriptors are sampled.

    python tools/bench_disk.py [--sizes 640x360,640x480,1024x576] [--runs 3] [--samples 20000]

Per image size (a synthetic room rendered at that size; DISK's cost does not depend on the
content): the median wall time of kornia's ``heatmap_and_dense_descriptors`` (the
network's dense output), of ``DISKExtractor.extract`` (its
keypoints and their descriptors), and of ``DISKExtractor.sample`` at ``--samples`` random
positions (what a build's training patches ask of a frame); the largest 1 - cosine between the
descriptors at the keypoints and the dense map's interpolated there; and the sampling state's size
against the dense map's. Needs the optional DISK packages (``bash tools/setup.sh --disk``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def median_time(runs: int, fn, *args) -> tuple[float, object]:
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="640x360,640x480,1024x576")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)

    import torch
    import torch.nn.functional as F

    from favormap import features
    from favormap.synthetic import camera_path, make_camera, make_room, render

    ex = features.create("disk", max_keypoints=4096, device=args.device)
    rng = np.random.default_rng(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    print(
        "| image | dense forward (s) | extract (s) | speed-up | sample "
        f"{args.samples} points (s) | keypoints | 1 - cos max | state MB (dense map MB) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.split("x"))
        img = render(make_room(0), make_camera(w, h), camera_path(3)[1])[0]
        x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float().div(255.0).to(args.device)
        x = F.pad(x, (0, (-w) % 16, 0, (-h) % 16))
        with torch.inference_mode():
            t_dense, (_, desc) = median_time(args.runs, ex.model.heatmap_and_dense_descriptors, x)
        t_extract, f = median_time(args.runs, ex.extract, img)
        pts = rng.uniform([0, 0], [w, h], (args.samples, 2)).astype(np.float32)
        t_sample, _ = median_time(args.runs, ex.sample, f, pts)
        dense = desc[0, :, :h, :w].permute(1, 2, 0).half().float().cpu().numpy()
        p = np.clip(f.keypoints - 0.5, 0, [w - 1, h - 1])
        x0, y0 = np.minimum(np.floor(p).astype(int), [w - 2, h - 2]).T
        fx, fy = (p - np.c_[x0, y0]).T[..., None]
        ref = (dense[y0, x0] * (1 - fx) + dense[y0, x0 + 1] * fx) * (1 - fy) + (
            dense[y0 + 1, x0] * (1 - fx) + dense[y0 + 1, x0 + 1] * fx
        ) * fy
        cos = np.sum(f.descriptors * ref / np.linalg.norm(ref, axis=1, keepdims=True), axis=1)
        state_mb = f.dense.hidden.numel() * 2 / 1e6
        print(
            f"| {w}x{h} | {t_dense:.2f} | {t_extract:.2f} | {t_dense / t_extract:.1f}x | {t_sample:.2f} | "
            f"{len(f)} | {1 - cos.min():.1e} | {state_mb:.0f} ({dense.size * 2 / 1e6:.0f}) |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
