"""favormap localize map.h5 query.png --prior pose.txt | favormap localize map.h5 queries/ --priors priors.txt"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..localize.config import LocalizeConfig, SuccessChecks
from ..threads import add_threads_arg
from ..viz import add_rerun_args, recording_from_args
from .common import auto_device, config_default, print_json
from .queries import IMAGE_EXT, Query, read_queries, write_poses


def open_map(args):
    """The map of a localize / eval command, its voxel cache sized by --cache-mb."""
    from ..errors import InputError
    from ..mapfile import Map

    mb = getattr(args, "cache_mb", None)
    if mb is not None and mb < 1:
        raise InputError("--cache-mb must be at least 1")
    return Map.open(args.map, cache_bytes=None if mb is None else mb << 20)


def add_localize_options(p):
    # long: one argparse option table (shared with `favormap eval`), split would scatter it
    p.add_argument(
        "--cache-mb",
        type=int,
        default=None,
        metavar="MB",
        help="memory for the voxel grids read from the map (default 1024: the whole map where it fits; a larger "
        "map is read as the queries need it)",
    )
    p.add_argument(
        "--iters",
        type=int,
        default=config_default(LocalizeConfig, "iterations"),
        help="render-match-PnP iterations, at most (default %(default)s; they stop once the estimate stops moving)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=None,
        help="descriptor similarity threshold (default: the map's extractor's policy)",
    )
    p.add_argument(
        "--max-keypoints",
        type=int,
        default=config_default(LocalizeConfig, "max_keypoints"),
        help="query keypoints (default %(default)s)",
    )
    p.add_argument(
        "--ransac-px",
        type=float,
        default=config_default(LocalizeConfig, "ransac_max_error_px"),
        help="RANSAC inlier threshold in pixels of the map's working resolution (default: the map's, "
        f"{config_default(LocalizeConfig, 'min_ransac_px'):g} px or "
        f"{config_default(LocalizeConfig, 'pose_noise_ransac'):g} times its epipolar limit where its mapping poses "
        "fit their images less well; where that is wider, each rendering iteration's estimate is fitted to the "
        "matches within "
        f"{config_default(LocalizeConfig, 'fit_max_error_px'):g} px of it)",
    )
    p.add_argument(
        "--min-inliers",
        type=int,
        default=config_default(SuccessChecks, "min_inliers"),
        help="inliers needed for success (default %(default)s)",
    )
    p.add_argument("--no-mutual", action="store_true", help="do not require mutual nearest-neighbour matches")
    p.add_argument(
        "--ratio",
        type=float,
        default=config_default(LocalizeConfig, "ratio"),
        help="Lowe ratio test on descriptor distances in the rendering iterations (1: off; default %(default)s; "
        "matching without a prior uses the extractor's policy)",
    )
    p.add_argument(
        "--landmark-sigma",
        default=config_default(LocalizeConfig, "landmark_sigma_px"),
        help="final refinement weighted by each landmark's position uncertainty, for this keypoint noise of the "
        "mapping images: 'landmark' (each landmark's, from its reprojection error), 'map' (their "
        "median), a number of pixels, or 0 (off: RANSAC's refinement only); default %(default)s",
    )
    p.add_argument(
        "--guided-radius",
        type=float,
        default=config_default(LocalizeConfig, "guided_radius_px"),
        help="guided step after the iterations: match every visible landmark to the query keypoints this close "
        "(px) to its projection and within 3 sigma of its predicted uncertainty, and solve again "
        "(0: off; default %(default)s; docs/accuracy.md)",
    )
    p.add_argument(
        "--guided-below",
        type=int,
        default=config_default(LocalizeConfig, "guided_below_inliers"),
        help="run the guided step only for poses with fewer inliers matched by descriptor than this "
        "(a large number: every pose; default %(default)s)",
    )
    p.add_argument(
        "--align",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="before the final refinement, align each inlier's keypoint to the mapping image that saw its landmark "
        "from the nearest direction, through the landmark's local plane (needs the mapping images, or a map built "
        "with --align-patches; docs/accuracy.md). Default: what the map asks for (`favormap info`): on for maps "
        "built with --exact-poses and for DISK and "
        "ALIKED maps, off for SIFT maps",
    )
    p.add_argument(
        "--mapping-images",
        help="--align: the folder of the map's mapping sequence (default: the observation patches the map stores, "
        "else the folder the map was built from)",
    )
    p.add_argument(
        "--align-references",
        type=int,
        default=None,
        metavar="N",
        help="--align: align each inlier to its landmark's N mapping images nearest in direction and average "
        f"(default {config_default(LocalizeConfig, 'align_references')})",
    )
    p.add_argument(
        "--no-global",
        action="store_true",
        help="never fall back to matching against all landmarks when the prior fails (or is missing)",
    )
    p.add_argument(
        "--device",
        default="auto",
        help="auto (a GPU where torch sees one), cpu (NumPy rendering: torch is not loaded for a SIFT map) or cuda",
    )
    add_threads_arg(p)
    p.set_defaults(threads_by_api=True)  # the Localizer sizes the pools (favormap.threads)


def register(sub):
    p = sub.add_parser(
        "localize",
        help="localize query image(s) against a map from a pose prior",
        description="Render the descriptors of the landmarks visible from the prior, match them to the "
        "query's features and solve PnP-RANSAC, iteratively. Pose files: a 4x4 world_from_cam "
        "matrix (OpenCV axes) or one line 'tx ty tz qx qy qz qw' (TUM).",
    )
    p.add_argument("map")
    p.add_argument("query", help="query image, or a folder of images (with --priors)")
    p.add_argument(
        "--prior",
        help="pose file of the prior (world_from_cam); without it a coarse pose is found by "
        "matching against all landmarks",
    )
    p.add_argument(
        "--priors",
        help="for a folder: text file with lines 'IMAGE_NAME tx ty tz qx qy qz qw' or "
        "'IMAGE_NAME' + 16 numbers (world_from_cam, row-major); without it, no priors",
    )
    p.add_argument(
        "--sequential",
        action="store_true",
        help="for a folder: the images (in name order) are a stream from one camera; each image's prior comes "
        "from the poses estimated before it (--motion), so only the first needs one (--prior) or none",
    )
    p.add_argument(
        "--motion",
        choices=["constant-velocity", "previous"],
        default=None,
        help="with --sequential: the next prior is the last localized pose moved on by the motion between the "
        "last two frames (constant-velocity, default) or that pose as it is (previous)",
    )
    p.add_argument(
        "--fixed-landmarks",
        action="store_true",
        help="with --sequential: keep the map's landmark positions (by default the landmarks each localized image "
        "saw are triangulated again with its observations, for the images after it; the map file is not changed)",
    )
    p.add_argument("--camera", help="query camera: a COLMAP camera line or JSON (default: the map's camera)")
    p.add_argument(
        "--descriptors",
        choices=["rendered", "mean"],
        default=config_default(LocalizeConfig, "descriptors"),
        help="landmark descriptors: rendered from the voxels (FaVoR) or each landmark's stored mean (default "
        "%(default)s)",
    )
    add_localize_options(p)
    p.add_argument(
        "--output", help="write the estimated pose (world_from_cam 4x4) here; for a folder: one line per image"
    )
    p.add_argument("--json", action="store_true", help="one JSON object per query")
    add_rerun_args(p)
    p.set_defaults(func=run)


def config_from_args(args):
    from ..errors import InputError
    from ..localize import LocalizeConfig, SuccessChecks

    if args.iters < 1:
        raise InputError("--iters must be >= 1")
    if args.threshold is not None and not 0 < args.threshold <= 1:
        raise InputError("--threshold must be in (0, 1]")
    if not 0 < args.ratio <= 1:
        raise InputError("--ratio must be in (0, 1]")
    if args.ransac_px is not None and not 0 < args.ransac_px < float("inf"):
        raise InputError("--ransac-px must be > 0")
    if args.min_inliers < 4:
        raise InputError("--min-inliers must be >= 4")
    guided = getattr(args, "guided_radius", None)
    guided = LocalizeConfig.guided_radius_px if guided is None else guided
    if not 0 <= guided < float("inf"):
        raise InputError("--guided-radius must be a number of pixels >= 0")
    guided_below = getattr(args, "guided_below", None)
    guided_below = LocalizeConfig.guided_below_inliers if guided_below is None else guided_below
    if guided_below is not None and guided_below < 0:
        raise InputError("--guided-below must be a number of inliers >= 0")
    sigma = getattr(args, "landmark_sigma", config_default(LocalizeConfig, "landmark_sigma_px"))
    if sigma not in ("landmark", "map"):
        try:
            sigma = float(sigma)
        except ValueError:
            sigma = -1.0
        if not (sigma >= 0 and sigma < float("inf")):
            raise InputError("--landmark-sigma must be 'landmark', 'map' or a number of pixels >= 0")
    align = getattr(args, "align", None)  # None: the map's choice (on for --exact-poses, DISK and ALIKED maps)
    images = getattr(args, "mapping_images", None)
    if images is not None and not align:
        raise InputError("--mapping-images is for --align")
    refs = getattr(args, "align_references", None)
    if refs is not None and not align:
        raise InputError("--align-references is for --align")
    if refs is not None and not 1 <= refs <= 64:
        raise InputError("--align-references must be between 1 and 64")
    return LocalizeConfig(
        align=align,
        align_images=images,
        **({} if refs is None else {"align_references": refs}),  # not given: LocalizeConfig's default
        iterations=args.iters,
        match_threshold=args.threshold,
        max_keypoints=args.max_keypoints,
        ransac_max_error_px=args.ransac_px,
        checks=SuccessChecks(min_inliers=args.min_inliers),
        mutual=not args.no_mutual,
        ratio=args.ratio,
        global_fallback=not args.no_global,
        descriptors=getattr(args, "descriptors", config_default(LocalizeConfig, "descriptors")),
        landmark_sigma_px=sigma,
        guided_radius_px=guided,
        guided_below_inliers=guided_below,
        device=auto_device(args.device),
        threads=getattr(args, "threads", None) or "auto",  # the CLI sizes the pools (favormap.threads)
    )


def run(args) -> int:
    from ..io.posefile import read_camera, read_pose
    from ..localize import Localizer

    query = Path(args.query)
    sequential = _check_args(args, query)
    queries = read_queries(args, query)
    config = config_from_args(args)
    first_prior = read_pose(args.prior) if sequential and args.prior else None
    m = open_map(args)
    camera = read_camera(args.camera) if args.camera else None
    loc = Localizer(m, config)
    rec = recording_from_args(args, "favormap localize", m)
    done = _localize_all(args, queries, loc, rec, camera, sequential, first_prior)
    if args.output:
        write_poses(Path(args.output), done, one=len(queries) == 1)
    failures = sum(not q.result.success for q in done)
    if failures:
        if not args.json:
            msgs = [f"{q.image.name}: {q.result.message}" for q in done if not q.result.success]
            print(f"favormap localize: {failures} of {len(queries)} queries not localized ({msgs[0]})", file=sys.stderr)
        return 2
    return 0


def _check_args(args, query: Path) -> bool:
    """The checks of the arguments before any work (the query exists, the output can be written, the
    options go together); returns whether the queries are localized as a sequence."""
    from ..errors import InputError

    if not query.exists():
        raise InputError(f"query not found: {query}")
    if args.output:  # before any work: a folder that exists and takes files, and not one of the inputs
        from ..mapfile.writer import check_output_path

        out = check_output_path(args.output, [args.map, query, args.prior, args.priors, args.camera])
        if query.is_dir() and out.suffix.lower() in IMAGE_EXT and out.resolve().parent == query.resolve():
            raise InputError(f"output {out} would be taken for a query image of {query}; write it elsewhere")
    sequential = getattr(args, "sequential", False)
    if sequential and not query.is_dir():
        raise InputError("--sequential localizes a folder of images; for one image give --prior")
    if sequential and args.priors:
        raise InputError(
            "--sequential takes its priors from the poses it estimates: give --prior for the first image, not --priors"
        )
    if not sequential and (getattr(args, "fixed_landmarks", False) or getattr(args, "motion", None)):
        raise InputError("--motion and --fixed-landmarks go with --sequential")
    if query.is_dir() and args.prior and not sequential:
        raise InputError("--prior is for one image (or the first of a --sequential folder); for a folder give --priors")
    return sequential


def _localize_all(args, queries: list[Query], loc, rec, camera, sequential: bool, first_prior) -> list[Query]:
    """Each query localized (one by one, or as a sequence: each prior from the estimates before it, the
    landmarks refined as it goes), printed and recorded as it comes; returns those localized, with
    their results. Closes the localizer and the recording."""
    done = []
    if sequential:  # each prior from the estimates before it; the landmarks refined as it goes
        refine = not args.fixed_landmarks
        results = loc.localize_sequence(
            [q.image for q in queries], first_prior, camera, args.motion or "constant-velocity", refine
        )
    else:
        refine, results = False, (loc.localize(q.image, q.prior, camera) for q in queries)
    try:
        for i, (q, res) in enumerate(zip(queries, results)):
            if rec is not None:
                if refine:
                    rec.log_refined_landmarks(i, loc.positions, loc.map.positions)
                rec.log_localization(i, str(q.image), res, res.prior, camera=camera, positions=loc.positions)
            if args.json:
                print_json({"query": str(q.image), **res.to_json()})
            else:
                print_result(str(q.image), res)
            q.result = res
            done.append(q)
    finally:
        if sequential:
            results.close()  # the stream hands the localizer the map's landmarks back
        loc.close()
        if rec is not None:
            rec.close()
    return done


def print_result(name: str, res) -> None:
    import numpy as np

    from ..geometry import camera_centers, inverse, rotmat_to_quat

    T = res.cam_from_world
    status = "localized" if res.success else f"NOT localized: {res.message}"
    print(f"{name}: {status}")
    # "iter k" for the rendering iterations; the prior-free coarse pose and the guided step by name
    k = 0
    for it in res.iterations:
        c = camera_centers(it.cam_from_world)
        k += it.kind == "render"
        label = {"global": "no prior:", "guided": "guided:"}.get(it.kind, f"iter {k}:")
        print(
            f"  {label:<12} visible {it.num_visible:5d}  matches {it.num_matches:5d}  inliers {it.num_inliers:5d}  "
            f"camera centre in world ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) scene units"
        )
    if res.success:
        for label, P in (("cam_from_world", T), ("world_from_cam", inverse(T))):
            q = rotmat_to_quat(P[:3, :3])
            print(
                f"  {label}: q_xyzw ({', '.join(f'{v:.6f}' for v in q)})  t "
                f"({', '.join(f'{v:.6f}' for v in P[:3, 3])}) scene units"
            )
        if res.covariance is not None:
            sd = res.covariance.center_std
            print(
                f"  uncertainty (1 sigma): camera centre ({', '.join(f'{v:.4f}' for v in sd)}) scene units along "
                f"x, y, z; rotation {res.covariance.rotation_std_deg:.3f} deg"
            )
            cov = res.covariance
            if cov.landmark_scale is not None:
                print(
                    f"  noise model fitted to the inliers: landmark position errors {cov.landmark_scale:.2f}x "
                    f"the map's variance, keypoint noise {cov.keypoint_sigma_px:.2f} px"
                )
    if res.aligned is not None:
        print(
            f"  {int(np.isfinite(res.aligned[:, 0]).sum())} of {res.num_inliers} inlier keypoints aligned to the "
            "mapping images (--align)"
        )
    print("  timings (ms): " + ", ".join(f"{k} {1000 * v:.1f}" for k, v in res.timings.items()))
