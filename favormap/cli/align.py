"""favormap align a.h5 b.h5 [-o b_to_a.txt] [--json]"""

from __future__ import annotations

from ..ops.align_config import AlignConfig
from .common import config_default, print_json


def add_align_args(p) -> None:
    """The alignment options shared by ``align`` and ``merge --align``."""
    p.add_argument(
        "--align-threshold",
        type=float,
        metavar="D",
        help="inlier distance in the first map's units (default: twice its median voxel size)",
    )
    p.add_argument(
        "--min-inliers",
        type=int,
        default=config_default(AlignConfig, "min_inliers"),
        metavar="N",
        help="refuse below N agreeing landmarks (default %(default)s)",
    )
    p.add_argument(
        "--min-inlier-ratio",
        type=float,
        default=config_default(AlignConfig, "min_inlier_ratio"),
        metavar="F",
        help="refuse when fewer than this fraction of landmark matches agree (default %(default)s)",
    )


def align_config(args):
    from ..errors import InputError

    if args.min_inliers < 3:
        raise InputError(f"--min-inliers must be >= 3, got {args.min_inliers}")
    if not 0 <= args.min_inlier_ratio <= 1:
        raise InputError(f"--min-inlier-ratio must be in [0, 1], got {args.min_inlier_ratio}")
    if args.align_threshold is not None and not args.align_threshold > 0:
        raise InputError(f"--align-threshold must be > 0, got {args.align_threshold}")
    return AlignConfig(
        threshold=args.align_threshold, min_inliers=args.min_inliers, min_inlier_ratio=args.min_inlier_ratio
    )


def register(sub):
    p = sub.add_parser(
        "align",
        help="estimate the similarity b_to_a between two maps of one place",
        description="Estimate the similarity transform b_to_a (scale, rotation, translation) that moves map "
        "b into map a's frame, from their landmarks alone: mutual descriptor matches, 3D-3D RANSAC with "
        "scale, then the similarity refined over the keypoints of both maps' frames that saw the matched "
        "landmarks, with a jackknife uncertainty over blocks of frames. Refuses when the maps do not "
        "overlap enough. The -o file is what 'favormap merge --transform' reads.",
    )
    p.add_argument("a", help="the map whose frame is kept")
    p.add_argument("b", help="the map to move")
    p.add_argument("-o", "--output", metavar="FILE", help="write the 4x4 b_to_a matrix here")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_align_args(p)
    p.set_defaults(func=run)


def summary_lines(r) -> list[str]:
    return [
        f"matches             {r.num_matches} between {r.num_landmarks[0]} and {r.num_landmarks[1]} landmarks",
        f"inliers             {r.num_inliers} ({100 * r.inlier_ratio:.1f} %), residual RMS {r.rms:.4g} "
        f"(threshold {r.threshold:.4g}, inlier extent {r.extent:.4g})",
        f"refined on          {r.num_refined_matches} matches, {r.num_observations} observations, "
        f"reprojection RMS {r.reprojection_rms_px:.3g} px",
        f"scale               {r.scale:.6g} (std of log-scale {r.std_log_scale:.2g})",
        f"rotation            {r.rotation_deg:.3f} deg (std {r.std_rotation_deg:.3g} deg)",
        "translation         "
        + " ".join(f"{v:.6g}" for v in r.b_to_a[:3, 3])
        + " (std "
        + " ".join(f"{v:.3g}" for v in r.std_translation_xyz)
        + ")",
    ]


def print_warnings(command: str, warnings) -> None:
    import sys

    for w in warnings:
        print(f"favormap {command}: warning: {w}", file=sys.stderr)


def run(args) -> int:
    from ..ops.align import align_maps, write_transform

    cfg = align_config(args)
    r = align_maps(args.a, args.b, cfg)
    if args.output:
        write_transform(args.output, r.b_to_a)
    if args.json:
        d = r.to_dict()
        d["output"] = args.output
        print_json(d)
        return 0
    for line in summary_lines(r):
        print(line)
    print_warnings("align", r.warnings)
    if args.output:
        print(f"b_to_a              {args.output}")
    else:
        for row in r.b_to_a:
            print("  " + " ".join(f"{v: .9g}" for v in row))
    return 0
