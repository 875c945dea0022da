"""How far a map's landmarks lie from where the query images see them (a map-geometry diagnostic).

For each query of a split with ground-truth poses, every landmark visible at the ground-truth pose
is paired with the query keypoint within ``--radius`` px of its projection whose descriptor is most
similar to the landmark's stored mean descriptor (cosine >= ``--min-cosine``); the distance
between that keypoint and the projection is the landmark's error as this query sees it (plus the
query keypoint's own noise and the ground truth's). No localization runs, so it isolates the map's
geometry from the localizer: far from the mapping path (fox-extrap) the errors are several times
those of the hold-out views, and they fall with the landmark's track length.

    python tools/bench_landmarks.py --map /tmp/acc/fox-extrap.h5 --split fox-extrap
    python tools/bench_landmarks.py --map /tmp/acc/fox-holdout.h5 --split fox-holdout --json out.json

The maps are those ``tools/bench_accuracy.py --workdir DIR`` builds (DIR/SPLIT.h5); the split's
queries are read from ../shared/data/fox (FAVORMAP_FOX). Columns: pairs, median distance (px),
share within 1 px, 90th percentile, per bin of track length and of the angle between the query's
viewing ray and the landmark's mean training ray.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

LENGTH_BINS = ((3, 4), (4, 6), (6, 9), (9, 10_000))
RAY_ANGLE_BINS = ((0, 20), (20, 35), (35, 50), (50, 180))


def landmark_residuals(m, queries, max_side: int, radius: float, min_cosine: float) -> dict[str, np.ndarray]:
    """Per (query, landmark) pair: query index, landmark row, distance (px) and ray angle (deg)."""
    from favormap.build import ExtractorSpec, extract_sequence
    from favormap.geometry import camera_centers, project

    ff = extract_sequence(queries, ExtractorSpec(m.extractor, 4096), max_side)
    pos = np.asarray(m.positions[:], np.float64)
    desc = np.asarray(m.mean_descriptors(np.arange(len(m))), np.float32)
    view_dir = np.asarray(m.view_dir[:], np.float64)
    out = {k: [] for k in ("query", "landmark", "distance_px", "ray_angle_deg")}
    for i, f in enumerate(ff.features):
        T = ff.cam_from_world[i]
        uv, z = project(ff.cameras[i].K, T, pos, with_depth=True)
        w, h = f.image_size
        vis = np.flatnonzero((z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h))
        if not len(vis) or not len(f):
            continue
        d = np.linalg.norm(uv[vis, None] - f.keypoints[None].astype(np.float64), axis=2)
        sim = desc[vis] @ f.descriptors.T
        sim[d > radius] = -np.inf
        k = sim.argmax(axis=1)
        rows = np.arange(len(vis))
        ok = sim[rows, k] >= min_cosine
        ray = camera_centers(T[None])[0] - pos[vis[ok]]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        cos = np.clip(np.einsum("ij,ij->i", ray, view_dir[vis[ok]]), -1, 1)
        out["query"].append(np.full(ok.sum(), i))
        out["landmark"].append(vis[ok])
        out["distance_px"].append(d[rows, k][ok])
        out["ray_angle_deg"].append(np.degrees(np.arccos(cos)))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def summary(dist: np.ndarray) -> dict:
    if not len(dist):
        return {"pairs": 0}
    return {
        "pairs": int(len(dist)),
        "median_px": float(np.median(dist)),
        "within_1px": float(np.mean(dist <= 1.0)),
        "p90_px": float(np.percentile(dist, 90)),
    }


def table(res: dict[str, np.ndarray], track_length: np.ndarray) -> list[dict]:
    L = track_length[res["landmark"].astype(np.int64)]
    rows = [dict(bin="all", **summary(res["distance_px"]))]
    for lo, hi in LENGTH_BINS:
        sel = (L >= lo) & (L < hi)
        label = f"{lo}" if hi == lo + 1 else (f">= {lo}" if hi == 10_000 else f"{lo}-{hi - 1}")
        rows.append(dict(bin=f"track length {label}", **summary(res["distance_px"][sel])))
    for lo, hi in RAY_ANGLE_BINS:
        sel = (res["ray_angle_deg"] >= lo) & (res["ray_angle_deg"] < hi)
        rows.append(dict(bin=f"ray angle {lo}-{hi} deg", **summary(res["distance_px"][sel])))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", required=True, help="a map of the split's mapping frames (tools/bench_accuracy.py's)")
    ap.add_argument("--split", default="fox-extrap", choices=("fox-holdout", "fox-extrap"))
    ap.add_argument("--radius", type=float, default=6.0, help="search radius around the projection (px)")
    ap.add_argument("--min-cosine", type=float, default=0.85, help="descriptor similarity a pair needs")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)

    import bench_accuracy as bench  # noqa: I001 (tools/, on the path above)
    from favormap.mapfile import Map

    splits = bench.fox_splits([args.split])
    if not splits:
        print(f"error: {bench.FOX} not found (set FAVORMAP_FOX)", file=sys.stderr)
        return 2
    with Map.open(args.map) as m:
        res = landmark_residuals(m, splits[0].queries, m.max_side, args.radius, args.min_cosine)
        rows = table(res, np.asarray(m.track_length[:]))
    print(
        f"{args.map}: {args.split}, {len(splits[0].queries)} queries, radius {args.radius} px, "
        f"cosine >= {args.min_cosine}"
    )
    print("| landmarks seen | pairs | median px | within 1 px | p90 px |\n|---|---|---|---|---|")
    for r in rows:
        if r["pairs"]:
            print(f"| {r['bin']} | {r['pairs']} | {r['median_px']:.2f} | {r['within_1px']:.2f} | {r['p90_px']:.2f} |")
        else:
            print(f"| {r['bin']} | 0 | - | - | - |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
