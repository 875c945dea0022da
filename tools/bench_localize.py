#!/usr/bin/env python3
"""Warm per-query localization time, split by stage, on a synthetic room map at 640x480.

    python tools/bench_localize.py [--map MAP.h5 --sequence SEQ] [--queries 10]

Without --map, renders a 30-frame 640x480 synthetic room, builds a map with up to 1500 landmarks
and localizes held-out views from priors perturbed by 0.3 units / 15 degrees.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map")
    ap.add_argument("--queries", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--descriptors", default="rendered")
    args = ap.parse_args()

    from favormap.build import BuildConfig, build_map
    from favormap.geometry import perturb_pose, pose_error
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map
    from favormap.synthetic import make_room, random_views_near, render, write_sequence

    tmp = tempfile.TemporaryDirectory()
    seq = write_sequence(Path(tmp.name) / "room", n_frames=30, width=640, height=480)
    path = args.map
    if path is None:
        path = Path(tmp.name) / "room.h5"
        t = time.perf_counter()
        write_map(build_map(seq, BuildConfig(max_landmarks=1500), device=args.device), path)
        print(f"built map in {time.perf_counter() - t:.1f} s")
    scene = make_room(0)
    cam = seq.cameras[0]
    views = random_views_near([f.cam_from_world for f in seq.frames], args.queries, seed=1, scene=scene)
    images = [render(scene, cam, T)[0] for T in views]
    rng = np.random.default_rng(0)
    loc = Localizer(path, LocalizeConfig(device=args.device, descriptors=args.descriptors))
    loc.localize(images[0], perturb_pose(views[0], 0.3, 15, rng))  # warm-up (model, caches)
    rows, errs, totals = [], [], []
    for img, T in zip(images, views):
        prior = perturb_pose(T, 0.3, 15, rng)
        t = time.perf_counter()
        res = loc.localize(img, prior)
        totals.append(time.perf_counter() - t)
        rows.append(res.timings)
        errs.append(pose_error(res.cam_from_world, T))
    keys = list(rows[0])
    print(
        f"map {path}: {len(loc.map)} landmarks; {len(views)} queries 640x480, 3 iterations, device {args.device}, "
        f"descriptors {args.descriptors}"
    )
    print(f"{'stage':<12} {'ms/query':>9}")
    for k in keys:
        print(f"{k:<12} {1000 * np.mean([r[k] for r in rows]):>9.1f}")
    print(f"{'total':<12} {1000 * np.mean(totals):>9.1f}")
    e = np.array(errs)
    print(f"median error {np.median(e[:, 0]):.4f} units / {np.median(e[:, 1]):.3f} deg")


if __name__ == "__main__":
    sys.exit(main())
