#!/usr/bin/env python3
"""Rendered against mean descriptors on real queries: which one looks more like what the query sees.

Each query is localized (rendered descriptors, the given prior mode); at the estimated pose, every
landmark visible from it that has a query keypoint within --radius px of its projection is compared:
the keypoint's descriptor against the landmark's descriptor rendered from the voxel grids at that pose
and against its mean observed descriptor (cosine). The pairs are chosen by geometry alone, so that
neither descriptor's matching picks them. The
pairs are binned by the angle, at the landmark, between the query camera and the nearest mapping
camera that observed it (the view change rendering is meant to follow). The estimated pose, not the
ground truth, places the landmarks: on sets whose ground truth disagrees with the images by pixels
(TUM RGB-D, ~1-2 cm) the estimate is the closer of the two.

    python tools/diagnose_descriptors.py --map desk.h5 --queries path/to/rgbd_dataset_freiburg1_xyz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BINS = ((0, 10), (10, 20), (20, 40), (40, 180))


def nearest_view_angles(m, rows: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(len(rows),) degrees between the query centre and the nearest mapping camera that observed each
    landmark, seen from the landmark."""
    from favormap.geometry import camera_centers

    lm, fr, _ = m.tracks()
    keep = np.isin(lm, rows)
    lm, fr = lm[keep], fr[keep]
    X = m.positions[lm]
    to_map = camera_centers(m.cam_from_world)[fr] - X
    to_query = center - X
    cos = np.sum(to_map * to_query, 1) / np.maximum(
        np.linalg.norm(to_map, axis=1) * np.linalg.norm(to_query, axis=1), 1e-300
    )
    best = np.full(len(m), -1.0)
    np.maximum.at(best, lm, cos)
    return np.degrees(np.arccos(np.clip(best[rows], -1.0, 1.0)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", required=True)
    ap.add_argument("--queries", required=True, help="a posed sequence (its poses give the priors)")
    ap.add_argument("--prior", default="nearest", help="prior mode (noise | nearest | none; default nearest)")
    ap.add_argument("--every", type=int, default=1, help="every N-th query")
    ap.add_argument("--radius", type=float, default=2.0, help="px between a projection and its keypoint (default 2)")
    args = ap.parse_args()

    from favormap.geometry import camera_centers, project
    from favormap.io import read_sequence
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.descriptors import describe, unit_rows
    from favormap.localize.evaluate import EvalConfig, make_priors
    from favormap.localize.matching import radius_pairs
    from favormap.mapfile import Map

    m = Map.open(args.map)
    seq = read_sequence(args.queries)
    seq = seq.subset(list(range(0, len(seq), max(args.every, 1))))
    loc = Localizer(m, LocalizeConfig())
    priors = make_priors(seq, m.rig_from_world, EvalConfig(prior_mode=args.prior))
    angles, c_rend, c_mean = [], [], []
    t0 = time.perf_counter()
    for fr, prior in zip(seq.frames, priors):
        cam = seq.cameras[fr.camera_id]
        res = loc.localize(fr.image_path, prior, cam)
        if not res.success:
            continue
        img, wcam = loc.prepare(fr.image_path, cam)
        feats = loc.extractor.extract(img)
        qdesc = unit_rows(np.asarray(feats.descriptors, np.float32))
        T = res.cam_from_world
        vis = loc._visible(wcam, T, {"visibility": 0.0})
        li, kj = radius_pairs(project(wcam.K, T, m.positions[vis]), feats.keypoints, args.radius)
        if len(li) == 0:
            continue
        # each landmark with its nearest keypoint
        d = np.linalg.norm(project(wcam.K, T, m.positions[vis[li]]) - feats.keypoints[kj], axis=1)
        order = np.lexsort((d, li))
        first = order[np.r_[True, li[order][1:] != li[order][:-1]]]
        rows, q = vis[li[first]], qdesc[kj[first]]
        rend, drows = describe(loc.source, rows, T, {})
        if len(drows) != len(rows):  # one rendered descriptor per landmark
            continue
        mean = unit_rows(m.mean_descriptors(rows))
        c_rend.append(np.sum(unit_rows(rend) * q, 1))
        c_mean.append(np.sum(mean * q, 1))
        angles.append(nearest_view_angles(m, rows, camera_centers(T)))
    if not angles:
        print("no query localized", file=sys.stderr)
        return 1
    a, r, mn = (np.concatenate(v) for v in (angles, c_rend, c_mean))
    print(f"{len(a)} landmark-keypoint pairs of {len(angles)} localized queries ({time.perf_counter() - t0:.0f} s)\n")
    print("| angle to the nearest mapping view | pairs | cosine rendered | cosine mean | rendered closer |")
    print("|---|---|---|---|---|")
    for lo, hi in BINS + ((0, 180),):
        sel = (a >= lo) & (a < hi)
        if sel.any():
            name = "all" if (lo, hi) == (0, 180) else f"{lo}-{hi} deg"
            print(
                f"| {name} | {sel.sum()} | {r[sel].mean():.3f} | {mn[sel].mean():.3f} | "
                f"{100 * np.mean(r[sel] > mn[sel]):.0f} % |"
            )
    m.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
