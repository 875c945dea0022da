#!/usr/bin/env python3
"""Accuracy of favormap against the structure baseline: one process, the same queries, one table.

For every split a favormap map is built from the mapping frames and localized against with
  - rendered descriptors (FaVoR), the default localizer;
  - the same map with each landmark's mean observed descriptor;
  - the same map with the descriptor observed in the nearest mapping frame;
  - (``--variants``) other localizer settings, e.g. the pre-benchmark defaults;
and the pycolmap structure baseline (SIFT, triangulation from the known poses, one mean descriptor
per point, LO-RANSAC PnP; favormap.localize.baseline) is built from the same frames and localized
without a prior. Prior modes: noise (ground truth moved by 0.3 units / 10 deg), nearest mapping
frame, constant (first mapping frame), none, sequential (the queries as a stream: the first without
a prior, each next one from the poses estimated before it, constant velocity), stream (sequential,
and the landmarks refined from the queries localized so far: favormap.localize.stream).

Splits:
  fox-holdout  ../shared/data/fox, map from frames i % 5 != 0, queries 0, 5, 10, ...
  fox-extrap   the same sequence, map from the first half of the path, queries: every frame of the
               second half (--extrap-step 2: every 2nd, the earlier set)
  orbit        a synthetic room orbit with exact ground truth, map from part of the arc, queries beyond it
               and off it, binned by the angle to the nearest mapping view
  orbit-dense  the orbit's map, 53 queries at 4-degree steps beyond both ends of the arc and raised
               above it, 14 of them 10-20 deg from the nearest view (not in the default set)
  custom       --map SEQ --queries SEQ (any readable sequences)

Columns: median / 90th-percentile translation (scene units, and % of the scene extent: the 5-95 %
bounding-box diagonal of the landmarks), median rotation, localized %, false successes (reported
success with error > 5 % of the extent or > 5 deg), mean inliers, median translation after each
iteration, seconds per query, and at the ground-truth pose the match precision (share of matches
within 2 px of the landmark's projection) and the keypoint repeatability (share of visible
landmarks with a query keypoint within 2 px); last, the noise floor (median over the localized
queries of how far the pose moves when its own inlier correspondences are re-drawn with Gaussian
noise of their residual scale, from the median reprojection error, and refined again:
favormap.localize.evaluate.pose_noise_floor) and that residual. A median error near the floor
means the correspondences are right and only more inliers or smaller residuals can lower it; far
above it, wrong or biased correspondences. NEES: the camera-centre error normalised by the
covariance the localizer reports with the pose (median over the localized queries; 2.37, the median
of a chi-square with 3 degrees of freedom, when that covariance is right; larger: overconfident).

    python tools/bench_accuracy.py                       # fox-holdout, fox-extrap, orbit
    python tools/bench_accuracy.py --splits orbit --json out.json
    python tools/bench_accuracy.py --map SEQ --queries SEQ
    python tools/bench_accuracy.py --compare before.json after.json   # two runs, query by query
    python tools/bench_accuracy.py --pool run1.json run2.json run3.json   # several runs, each query their median
"""

# The benchmark's parts are in tools/accuracy/ (imported from this folder, so the script runs from any directory):
#   accuracy/splits.py   the data and the splits: Split, REAL_SPLITS / CROSS_SPLITS / SUITES, real_splits, orbit_split
#   accuracy/runners.py  building the maps and localizing the queries: VARIANTS, build_or_load, run_split, record
#   accuracy/report.py   the rows as tables and statistics: paired_ratio, compare_table, real_table, markdown
# This file is the command line (main) and re-exports the names other tools and tests use as bench_accuracy.NAME.

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from accuracy.report import (
    PAIRED_BOOTSTRAP,
    compare_rows,
    compare_table,
    fmt_row,
    geometric_means,
    markdown,
    nees_with_ground_truth_error,
    paired_ratio,
    paired_rows,
    paired_table,
    pool_rows,
    read_rows,
    real_rows,
    real_table,
    seed_paired_rows,
    seed_paired_table,
    seed_table,
    shared_error,
    write_rows,
)
from accuracy.runners import (
    BEFORE_FIELD,
    DEFAULT_VARIANTS,
    VARIANTS,
    ReuseLastExtraction,
    build_key,
    build_or_load,
    localizer_config,
    median_over_priors,
    median_over_seeds,
    median_run,
    per_query,
    record,
    run_baseline,
    run_favormap,
    run_split,
    same_build,
)
from accuracy.splits import (
    ANGLE_BINS,
    BLURRED_SPLITS,
    CROSS_PRIORS,
    CROSS_SPLITS,
    DATA,
    EXTRA_SPLITS,
    FOX,
    REAL_RECALL,
    REAL_SETS,
    REAL_SPLITS,
    ROOT,
    SEVENSCENES_PGT,
    SUITES,
    Split,
    _natural_order,
    cross_split,
    fox_splits,
    nearest_view_angle,
    orbit_split,
    real_splits,
    with_pseudo_ground_truth,
)

# the benchmark's public names (and _natural_order), as before its split into accuracy/: other tools
# (diagnose_accuracy.py, bench_landmarks.py, bench_extend.py) and tests/test_setup.py use them as bench_accuracy.NAME
__all__ = [
    # accuracy/report.py
    "PAIRED_BOOTSTRAP",
    "compare_rows",
    "compare_table",
    "fmt_row",
    "geometric_means",
    "markdown",
    "nees_with_ground_truth_error",
    "paired_ratio",
    "paired_rows",
    "paired_table",
    "pool_rows",
    "read_rows",
    "real_rows",
    "real_table",
    "seed_paired_rows",
    "seed_paired_table",
    "seed_table",
    "shared_error",
    "write_rows",
    # accuracy/runners.py
    "BEFORE_FIELD",
    "DEFAULT_VARIANTS",
    "VARIANTS",
    "ReuseLastExtraction",
    "build_key",
    "build_or_load",
    "localizer_config",
    "median_over_priors",
    "median_over_seeds",
    "median_run",
    "per_query",
    "record",
    "run_baseline",
    "run_favormap",
    "run_split",
    "same_build",
    # accuracy/splits.py
    "ANGLE_BINS",
    "BLURRED_SPLITS",
    "CROSS_PRIORS",
    "CROSS_SPLITS",
    "DATA",
    "EXTRA_SPLITS",
    "FOX",
    "REAL_RECALL",
    "REAL_SETS",
    "REAL_SPLITS",
    "ROOT",
    "SEVENSCENES_PGT",
    "SUITES",
    "Split",
    "_natural_order",
    "cross_split",
    "fox_splits",
    "nearest_view_angle",
    "orbit_split",
    "real_splits",
    "with_pseudo_ground_truth",
]


def pooled_table(ap, paths: list[str]) -> int:
    """``--pool``: the real-data table of several runs, each query's error the median over the runs."""
    if len(paths) < 2:
        ap.error("--pool takes two or more runs")
    try:
        runs = [read_rows(f) for f in paths]
    except (OSError, ValueError) as e:
        ap.error(f"--pool: {e}")
    rows = pool_rows(runs)
    names = sorted({r["split"] for r in rows})
    splits = real_splits([n for n in names if n in REAL_SPLITS or n in CROSS_SPLITS or n in BLURRED_SPLITS])
    real = real_rows(rows, splits)
    if not real:
        print("--pool: no real split in all the runs (or its data is missing)", file=sys.stderr)
        return 1
    print(f"\nReal sets, {len(runs)} runs pooled (each query's error the median over the runs):\n")
    print(real_table(real))
    return 0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default="fox-holdout,fox-extrap,orbit")
    ap.add_argument(
        "--suite",
        choices=sorted(SUITES),
        help="the real-data suite (every set of ../shared/data read as shipped, the baseline side by side; "
        "real-quick: a subset; 7scenes-pgt: 7-Scenes with its shipped poses and with the SfM pseudo ground "
        "truth of the same frames): sets --splits, --priors noise, --variants rendered, --baseline-seeds 0,1,2 "
        "and --prior-seeds 0,1,2 unless given, and no per-query diagnostics",
    )
    ap.add_argument(
        "--baseline-seeds",
        default=None,
        help="the baseline's RANSAC seeds (comma-separated): each query's result is the seeds' median "
        "(default 0; the suite: 0,1,2)",
    )
    ap.add_argument(
        "--no-diagnostics",
        dest="diagnostics",
        action="store_false",
        help="skip the per-query diagnostics at the ground-truth pose (match precision, noise floor, NEES)",
    )
    ap.add_argument("--map", help="custom split: mapping sequence")
    ap.add_argument("--queries", help="custom split: query sequence")
    ap.add_argument("--priors", default="noise,nearest,constant,none,sequential,stream")
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=", ".join(VARIANTS).replace("%", "%%"))
    ap.add_argument(
        "--extractor",
        default=None,
        help="build with this extractor, or several (comma-separated: one map each, one table; "
        "default: the build default)",
    )
    ap.add_argument(
        "--solver",
        default=None,
        help="voxel training solver, or several (comma-separated: one map each; adam | lstsq; default: the build "
        "default, adam)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="VoxelConfig or BuildConfig override for every map built (repeatable; e.g. --set init=lstsq "
        "--set iterations=60)",
    )
    ap.add_argument(
        "--build-variant",
        action="append",
        default=[],
        metavar="NAME:KEY=VALUE,...",
        help="also build a map with these VoxelConfig or BuildConfig overrides (repeatable; one map each, its rows "
        "prefixed with NAME; e.g. --build-variant cf-dens20:solver=lstsq,density_init=20 or w6:match_window=6)",
    )
    ap.add_argument("--min-track", type=int, default=None)
    ap.add_argument("--max-landmarks", type=int, default=None)
    ap.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="Adam iterations (--quality fast / reference; the closed-form presets have none)",
    )
    ap.add_argument(
        "--quality",
        default=None,
        help="voxel training preset (quick | balanced | fast | reference; default: the build default)",
    )
    ap.add_argument("--device", default="cpu", help="torch device for training and localization (cpu | cuda)")
    ap.add_argument("--orbit-frames", type=int, default=24)
    ap.add_argument(
        "--extrap-step",
        type=int,
        default=1,
        help="fox-extrap queries: every STEP-th frame of the second half (default 1: 20 queries)",
    )
    ap.add_argument("--no-baseline", dest="baseline", action="store_false")
    ap.add_argument(
        "--baseline-budget", type=int, default=0, help="also run the baseline restricted to N longest tracks"
    )
    ap.add_argument("--workdir", default="/tmp/favormap-bench-accuracy")
    ap.add_argument("--reuse", action="store_true", help="reuse maps in --workdir built with the same settings")
    ap.add_argument("--seed", type=int, default=0, help="seed of the query priors")
    ap.add_argument(
        "--shuffle-mapping",
        type=int,
        default=None,
        metavar="SEED",
        help="list each split's mapping frames in a random order drawn with SEED (their maps and baselines kept "
        "apart from the listed order's): what a build makes of frames listed in no order",
    )
    ap.add_argument(
        "--prior-seeds",
        default=None,
        help="seeds of the noise priors (comma-separated): each query's favormap result is the median over "
        "its priors, as the baseline's is over --baseline-seeds (default: --seed alone)",
    )
    ap.add_argument(
        "--train-seeds",
        help="build every map once per voxel-training seed (e.g. 0,1,2; a seed K > 0 adds -sK to the map's "
        "name) and add a table of each method's median across the seeds: a rebuild with another seed moves "
        "the fox extrapolation median by ~11 %%, so compare variants over seeds",
    )
    ap.add_argument("--json", help="write all rows to this JSON file (gzip-compressed where it ends in .gz)")
    ap.add_argument(
        "--compare",
        nargs=2,
        metavar=("REF.json", "NEW.json"),
        help="run nothing: compare two runs' --json rows (plain or .gz) query by query (e.g. two versions of the code)",
    )
    ap.add_argument(
        "--pool",
        nargs="+",
        metavar="RUN.json",
        help="run nothing: the real-data table of several runs' --json rows of the same code, each query's error the "
        "median over the runs (the baseline's SfM map differs from build to build); needs the sets' data",
    )
    args = ap.parse_args()
    if args.shuffle_mapping is not None and args.shuffle_mapping < 0:
        ap.error(f"--shuffle-mapping {args.shuffle_mapping}: expected a seed >= 0")
    if args.pool:
        return pooled_table(ap, args.pool)
    if args.compare:
        try:
            ref_rows, new_rows = (read_rows(f) for f in args.compare)
        except (OSError, ValueError) as e:
            ap.error(f"--compare: {e}")
        table = compare_table(ref_rows, new_rows)
        print(table or "--compare: no (split, prior, map, method, seed) in both runs")
        return 0 if table else 1
    if args.suite:
        args.splits = ",".join(SUITES[args.suite])
        given = set(sys.argv)
        if "--priors" not in given:
            args.priors = "noise"
        if "--variants" not in given:
            args.variants = "rendered"
        args.diagnostics = False
        args.baseline_seeds = args.baseline_seeds or "0,1,2"
        args.prior_seeds = args.prior_seeds or "0,1,2"
    try:
        args.baseline_seeds = [int(x) for x in (args.baseline_seeds or "0").split(",") if x.strip()]
    except ValueError:
        ap.error(f"--baseline-seeds {args.baseline_seeds!r}: expected integers, e.g. 0,1,2")
    try:
        args.prior_seeds = [int(x) for x in (args.prior_seeds or str(args.seed)).split(",") if x.strip()]
    except ValueError:
        ap.error(f"--prior-seeds {args.prior_seeds!r}: expected integers, e.g. 0,1,2")
    if not args.prior_seeds:
        ap.error("--prior-seeds: no seed given")
    args.seed = args.prior_seeds[0]
    args.priors = [p for p in args.priors.split(",") if p]
    args.variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; known: {list(VARIANTS)}")

    from favormap import features
    from favormap.build import BuildConfig

    args.default_extractor = BuildConfig().extractor
    args.default_solver = BuildConfig().voxel.solver
    extractors = [e.strip() for e in (args.extractor or args.default_extractor).split(",") if e.strip()]
    bad = [e for e in extractors if e not in features.available()]
    if bad or not extractors:
        ap.error(f"unknown extractor(s) {bad}; known: {features.available()}")
    solvers = [s.strip() for s in (args.solver or "").split(",") if s.strip()] or [None]
    variants = [("", [])]
    for spec in args.build_variant:
        name, _, kvs = spec.partition(":")
        if not name or not kvs or not name.replace("-", "").replace(".", "").isalnum():
            ap.error(f"--build-variant {spec!r}: expected NAME:KEY=VALUE,... (NAME of letters, digits, - and .)")
        variants.append((name, [kv.strip() for kv in kvs.split(",") if kv.strip()]))
    train_seeds = [None]
    if args.train_seeds:
        try:
            train_seeds = sorted({int(x) for x in args.train_seeds.split(",") if x.strip()})
        except ValueError:
            ap.error(f"--train-seeds {args.train_seeds!r}: expected integers, e.g. 0,1,2")
        if any(kv.startswith("seed=") for kv in args.set + [kv for _, vs in variants for kv in vs]):
            ap.error("--train-seeds sets VoxelConfig.seed: leave seed= out of --set and --build-variant")
    build_cfgs = []
    for ex, solver, (vname, vset), seed in [
        (e, s, v, k) for e in extractors for s in solvers for v in variants for k in train_seeds
    ]:
        if seed:
            vset = vset + [f"seed={seed}"]
            vname = f"{vname}-s{seed}" if vname else f"s{seed}"
        build_cfg = BuildConfig(extractor=ex)
        if args.quality:
            from favormap.voxels import VoxelConfig

            build_cfg.voxel = VoxelConfig.preset(args.quality)
        if solver:
            build_cfg.voxel.solver = solver
        for kv in args.set + vset:
            k, _, v = kv.partition("=")
            target = build_cfg.voxel if hasattr(build_cfg.voxel, k) else build_cfg
            if not v or k == "voxel" or not hasattr(target, k):
                ap.error(f"{kv!r}: expected KEY=VALUE with KEY a VoxelConfig or BuildConfig field")
            setattr(target, k, json.loads(v) if v[:1] in '0123456789-[{tfn".' else v)
        for k in ("min_track", "max_landmarks"):
            if getattr(args, k) is not None:
                setattr(build_cfg, k, getattr(args, k))
        if args.iterations:
            build_cfg.voxel.iterations = args.iterations
        # construct again: the defaults that follow the fields set (exact_poses: refine_window, align_patches)
        build_cfg = dataclasses.replace(build_cfg)
        build_cfgs.append((vname, build_cfg))
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    splits: list[Split] = []
    if args.map or args.queries:
        from favormap.io import read_sequence

        if not (args.map and args.queries):
            ap.error("--map and --queries go together")
        mapping, queries = read_sequence(args.map), read_sequence(args.queries)
        splits.append(Split("custom", mapping, queries, nearest_view_angle(queries, mapping)))
    else:
        which = args.splits.split(",")
        real = [w for w in which if w in REAL_SPLITS or w in EXTRA_SPLITS or w in CROSS_SPLITS or w in BLURRED_SPLITS]
        if args.suite or any(w not in ("fox-holdout", "fox-extrap") for w in real):
            splits += real_splits(real)
        else:
            splits += fox_splits(which, args.extrap_step)
        if "orbit" in which:
            splits.append(orbit_split(workdir, args.orbit_frames, 640, 480))
        if "orbit-dense" in which:
            splits.append(orbit_split(workdir, args.orbit_frames, 640, 480, dense=True))
    if args.shuffle_mapping is not None:
        import numpy as np

        for sp in splits:
            perm = np.random.default_rng(args.shuffle_mapping).permutation(len(sp.mapping))
            sp.mapping = sp.mapping.subset([int(i) for i in perm])
            sp.map_name = f"{sp.files}-shuffled{args.shuffle_mapping}"
    rows = []
    for sp in splits:
        rows += run_split(sp, args, build_cfgs)
    print(markdown(rows))
    real = real_rows(rows, splits)
    if real:
        print(
            "\nReal sets, favormap (rendered, noise priors; median over prior seeds "
            + ",".join(map(str, args.prior_seeds))
            + ") and the baseline (median over RANSAC seeds "
            + ",".join(map(str, args.baseline_seeds))
            + ") on the same queries:\n"
        )
        print(real_table(real))
    paired = paired_table(rows)
    if paired:
        print("\n" + paired)
    if len(train_seeds) > 1:
        print("\nAcross training seeds " + ", ".join(map(str, train_seeds)) + ":\n")
        print(seed_table(rows, build_cfgs))
    if len(build_cfgs) > 1:
        print("\n" + seed_paired_table(rows, build_cfgs))
    builds = {
        (r["split"], r["extractor"] + r.get("solver_tag", "") + f" {r.get('map_variant', '')}".rstrip()): r["build_s"]
        for r in rows
        if "extractor" in r
    }
    build_cfg = build_cfgs[0][1]
    print(
        f"\n{len(splits)} splits in {time.perf_counter() - t0:.0f} s; build config: extractor {','.join(extractors)}, "
        f"min_track {build_cfg.min_track}, max_landmarks {build_cfg.max_landmarks}, "
        f"voxel solver {','.join(sorted({c.voxel.solver for _, c in build_cfgs}))} (adam: "
        f"{build_cfg.voxel.iterations} iterations x {build_cfg.voxel.rays_per_landmark} rays), "
        f"box factor {build_cfg.voxel.box_factor}, device {args.device}; map builds: "
        + ", ".join(f"{sp} {ex} {'reused' if b is None else f'{b:.0f} s'}" for (sp, ex), b in builds.items())
    )
    if args.json:
        write_rows(args.json, rows + ([{"real": real}] if real else []))


if __name__ == "__main__":
    sys.exit(main())
