#!/usr/bin/env python3
"""How favormap's tracks compare with the structure baseline's on the same features.

For each split (the splits of tools/bench_accuracy.py) the favormap map and the pycolmap-SIFT baseline
are built from the mapping frames (or reused from --workdir), and every baseline point of at least
--min-length observations whose observations meet a favormap landmark's (the same keypoint, within
--radius-px in the same frame) is followed through the baseline's track. Each of its observations is
counted as one of:

  in track       on the landmark that holds most of the point's observations
  other landmark on a keypoint of another landmark (the feature's track is split in two or more)
  not tracked    on a keypoint favormap's extractor finds in that frame (at the map's keypoint cap) that
                 no landmark holds; "beyond the window": none of the landmark's frames lies within the
                 map's matching window of this frame, so tracking never compared the two
  beyond the cap on a keypoint the extractor finds only without the map's keypoint cap
  not detected   no keypoint of favormap's extractor there

OpenCV's SIFT reports keypoints +0.25 px right of and below COLMAP's (its upscaling offset), so the
baseline's observations are shifted by that before they are looked up.

    python tools/diagnose_tracks.py --splits cup-holdout,office-holdout --reuse
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_accuracy as bench  # noqa: E402  (the splits and map builds of the benchmark)

OPENCV_OFFSET_PX = np.array([0.25, 0.25])  # OpenCV SIFT keypoint - COLMAP SIFT keypoint of one blob
KINDS = ("in track", "other landmark", "not tracked", "beyond the window", "beyond the cap", "not detected")


def count_observations(
    point: np.ndarray,
    frame: np.ndarray,
    xy: np.ndarray,
    tracks: tuple[np.ndarray, np.ndarray, np.ndarray],
    detected: list[np.ndarray],
    everywhere: list[np.ndarray],
    window: int,
    radius_px: float = 1.0,
    min_length: int = 3,
) -> tuple[int, Counter]:
    """The baseline points (observations ``point``, ``frame``, ``xy``, in favormap's pixel convention) of at
    least ``min_length`` observations that meet one of favormap's landmarks (``tracks``: landmark, frame, xy
    of every observation), and their observations counted by :data:`KINDS`. ``detected`` / ``everywhere``:
    per mapping frame, the keypoints favormap's extractor finds at the map's keypoint cap / without it."""
    from scipy.spatial import cKDTree

    landmark, lframe, lxy = tracks
    frame = np.asarray(frame, np.int64)
    # every observation looked up once per frame: the landmark that holds a keypoint within the radius (-1:
    # none), and whether favormap's extractor finds a keypoint there at the cap / without it
    owner = np.full(len(frame), -1, np.int64)
    found = np.zeros(len(frame), bool)
    anywhere = np.zeros(len(frame), bool)
    for f in np.unique(frame):
        obs = np.flatnonzero(frame == f)
        on = lframe == f
        if on.any():
            d, j = cKDTree(lxy[on]).query(xy[obs])
            owner[obs] = np.where(d <= radius_px, landmark[on][j], -1)
        for hit, keys in ((found, detected), (anywhere, everywhere)):
            if f < len(keys) and len(keys[f]):
                hit[obs] = cKDTree(keys[f]).query(xy[obs])[0] <= radius_px
    by_landmark = np.argsort(landmark, kind="stable")  # each landmark's frames, grouped once
    bounds = np.r_[np.unique(landmark[by_landmark], return_index=True)[1], len(landmark)]
    frames_of = {int(landmark[by_landmark[a]]): lframe[by_landmark[a:b]] for a, b in zip(bounds[:-1], bounds[1:])}

    counts: Counter = Counter()
    order = np.argsort(point, kind="stable")
    starts = np.searchsorted(point[order], np.arange(int(point.max(initial=-1)) + 2))
    points = 0
    for p in range(len(starts) - 1):
        obs = order[starts[p] : starts[p + 1]]
        if len(obs) < min_length or (owner[obs] < 0).all():
            continue
        points += 1
        main = np.bincount(owner[obs][owner[obs] >= 0]).argmax()
        main_frames = frames_of[int(main)]
        for o in obs:
            who, f = owner[o], frame[o]
            if who == main:
                counts["in track"] += 1
            elif who >= 0:
                counts["other landmark"] += 1
            elif found[o]:
                counts["beyond the window" if np.abs(main_frames - f).min() > window else "not tracked"] += 1
            elif anywhere[o]:
                counts["beyond the cap"] += 1
            else:
                counts["not detected"] += 1
    return points, counts


def split_tracks(split, args) -> dict:
    """The counts of one split (see the module's docstring)."""
    from favormap import features
    from favormap.build_config import BuildConfig
    from favormap.io import load_image
    from favormap.localize.baseline import StructureBaseline
    from favormap.mapfile import Map

    cfg = BuildConfig(extractor="sift")
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    path, _ = bench.build_or_load(split, workdir, cfg, args.reuse)
    base = StructureBaseline.build(split.mapping, workdir=workdir / f"{split.files}_baseline")
    with Map.open(path) as m:
        tracks = m.tracks()
    capped = features.create(cfg.extractor, max_keypoints=cfg.max_keypoints)
    uncapped = features.create(cfg.extractor, max_keypoints=1_000_000)
    detected, everywhere = [], []
    for fr in split.mapping.frames:
        img, _ = load_image(fr.image_path, split.mapping.cameras[fr.camera_id], cfg.max_side)
        detected.append(capped.extract(img).keypoints)
        everywhere.append(uncapped.extract(img).keypoints)
    t = base.tracks
    points, counts = count_observations(
        t.point,
        t.frame.astype(int),
        t.xy + OPENCV_OFFSET_PX,
        tracks,
        detected,
        everywhere,
        cfg.match_window,
        args.radius_px,
        args.min_length,
    )
    total = max(sum(counts.values()), 1)
    return {
        "split": split.name,
        "points": points,
        "observations": total,
        "shares": {k: round(counts[k] / total, 4) for k in KINDS},
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default="cup-holdout", help="comma-separated real splits of bench_accuracy.py")
    ap.add_argument("--workdir", default="bench_accuracy_work", help="maps and baselines (shared with the benchmark)")
    ap.add_argument("--reuse", action="store_true", help="reuse maps in --workdir built with the same settings")
    ap.add_argument("--min-length", type=int, default=3, help="baseline points of at least this many observations")
    ap.add_argument("--radius-px", type=float, default=1.0, help="how near a keypoint counts as the same (px)")
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args()
    if args.min_length < 2 or not args.radius_px > 0:
        ap.error("--min-length must be >= 2 and --radius-px > 0")
    names = [s for s in args.splits.split(",") if s]
    unknown = [s for s in names if s not in bench.REAL_SPLITS and s not in bench.EXTRA_SPLITS]
    if unknown or not names:
        ap.error(f"unknown split(s) {unknown}; known: {list(bench.REAL_SPLITS)}")
    splits = bench.real_splits(names)
    if not splits:
        print(f"error: none of the splits' sets found under {bench.DATA}", file=sys.stderr)
        return 1
    from favormap.errors import FavormapError

    results = []
    print("| split | baseline points | observations | " + " | ".join(KINDS) + " |")
    print("|---|---|---|" + "---|" * len(KINDS))
    try:
        for sp in splits:
            r = split_tracks(sp, args)
            results.append(r)
            cells = " | ".join(f"{100 * r['shares'][k]:.0f} %" for k in KINDS)
            print(f"| {r['split']} | {r['points']} | {r['observations']} | {cells} |", flush=True)
    except FavormapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
