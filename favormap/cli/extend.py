"""favormap extend map.h5 NEWSEQ -o bigger.h5 [--transform new_to_map.txt | --align]"""

from __future__ import annotations

import dataclasses
import sys

from ..ops.extend_config import ExtendConfig
from ..threads import add_threads_arg
from .build_sfm import add_sfm_args, estimate_poses_from_args, print_sfm_summary
from .common import StageBars, human_size, print_json

_DEFAULTS = {f.name: f.default for f in dataclasses.fields(ExtendConfig)}


def register(sub):
    p = sub.add_parser(
        "extend",
        help="add a capture to a map without rebuilding it",
        description="Add the frames of a posed sequence to a map: their features (the map's extractor settings) "
        "are tracked among themselves and matched to the map's landmarks by projection and descriptor; the "
        "landmarks that gain observations are triangulated again and their voxels fine-tuned, the new frames' "
        "other tracks become new landmarks. The result is written as a new map; the input is left as it is. "
        "Images without poses (a folder of photos, a video) are posed by structure from motion first and moved "
        "into the map's frame by --align.",
    )
    p.add_argument("map", help="the map to extend")
    p.add_argument(
        "sequence", help="the new posed sequence (any supported format), or a folder of images or a video without poses"
    )
    p.add_argument("-o", "--output", required=True, help="the extended map to write (not the input map)")
    p.add_argument("--format", help="force the sequence format instead of auto-detecting it")
    p.add_argument(
        "--transform",
        metavar="FILE",
        help="4x4 new_to_map similarity (x_map = s R x_new + t) moving the sequence's poses into the map's frame",
    )
    p.add_argument(
        "--align",
        action="store_true",
        help="estimate that similarity first, from a quick map of the sequence aligned to the map "
        "(as 'favormap align')",
    )
    p.add_argument(
        "--view-cone",
        type=float,
        default=_DEFAULTS["view_cone_deg"],
        metavar="DEG",
        help="attach a new observation only within DEG of the landmark's viewing cone (default %(default)s)",
    )
    p.add_argument(
        "--match-radius",
        type=float,
        default=_DEFAULTS["match_radius_px"],
        metavar="PX",
        help="a landmark takes a keypoint within PX of its projection (default: the epipolar limit of the map's "
        "tracking)",
    )
    p.add_argument(
        "--min-similarity",
        type=float,
        default=_DEFAULTS["min_similarity"],
        help="least descriptor cosine of such a keypoint (default: the map's tracking threshold)",
    )
    p.add_argument(
        "--max-landmarks",
        type=int,
        default=_DEFAULTS["max_landmarks"],
        metavar="N",
        help="landmarks of the extended map at most, the longest tracks kept as a build keeps them (default: the "
        "map's landmark budget, or its landmark count where that is larger)",
    )
    p.add_argument("--device", default=_DEFAULTS["device"], help="torch device of the training (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    add_threads_arg(p)
    add_sfm_args(p, scale=False, then="the extension (and --align implied)")
    p.set_defaults(func=run)


def _estimated_poses(args, out, progress):
    """The poses of new images without poses (an SfmResult), or None for a posed sequence."""
    from ..errors import InputError

    sfm = estimate_poses_from_args(args, out, progress)
    if sfm is not None and args.transform:
        raise InputError(
            "images without poses are posed in a frame of their own: --align moves them into the map's, not --transform"
        )
    return sfm


def run(args) -> int:
    from ..errors import InputError
    from ..io.posefile import read_transform
    from ..mapfile.writer import check_output_path
    from ..ops.extend import extend_map
    from .common import auto_device

    if args.align and args.transform:
        raise InputError("--align and --transform exclude each other")
    out = check_output_path(args.output, [args.map, args.sequence])  # before any work
    T = read_transform(args.transform)[0] if args.transform else None
    bars = StageBars(args.quiet or args.json)
    try:
        sfm = _estimated_poses(args, out, bars)
    finally:
        bars.close()
    config = ExtendConfig(
        transform=None if T is None else T.tolist(),
        align=args.align or sfm is not None,
        view_cone_deg=args.view_cone,
        match_radius_px=args.match_radius,
        min_similarity=args.min_similarity,
        max_landmarks=args.max_landmarks,
        format=args.format,
        device=auto_device(args.device),
    )
    try:
        s = extend_map(args.map, args.sequence if sfm is None else sfm.sequence, args.output, config, progress=bars)
    finally:
        bars.close()
    for w in s.warnings:
        print(f"favormap extend: warning: {w}", file=sys.stderr)
    from pathlib import Path

    d = s.to_dict()
    d["file_size"] = Path(args.output).stat().st_size
    if sfm is not None:
        d["poses"] = sfm.to_dict()
    if args.json:
        print_json(d)
        return 0
    if sfm is not None:
        print_sfm_summary(d["poses"], units=False)
    if s.alignment is not None:
        a = s.alignment
        print(
            f"aligned             {a['num_inliers']} of {a['num_matches']} landmark matches agree, "
            f"scale {a['scale']:.6g}, rotation {a['rotation_deg']:.3f} deg"
        )
    print(f"frames              {s.frames_before} + {s.frames_added}")
    print(
        f"landmarks           {s.landmarks_before} -> {s.landmarks_after}  ({s.landmarks_grown} grown by "
        f"{s.observations_added} observations, {s.landmarks_retrained} of them retrained; {s.landmarks_added} new; "
        f"{s.landmarks_removed} left out of the budget)"
    )
    print(f"file                {args.output}  ({human_size(d['file_size'])})")
    print("seconds per stage   " + ", ".join(f"{k} {v:.1f}" for k, v in s.timings.items()))
    return 0
