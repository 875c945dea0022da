"""favormap prune map.h5 -o small.h5 [--max-landmarks N] [--min-track K] [--min-quality Q] [--bbox x0,y0,z0,x1,y1,z1]"""

from __future__ import annotations

import re
from pathlib import Path

from ..threads import add_threads_arg
from ..viz import add_rerun_args, recording_from_args
from .common import StageBars, human_size, print_json


def register(sub):
    p = sub.add_parser(
        "prune",
        help="drop landmarks by track length, quality, region or to a budget",
        description="Write a smaller map: drop landmarks with short tracks, low training PSNR or outside a "
        "box, then meet a landmark budget keeping the best landmark of every occupied cell of "
        "a grid (spatially even coverage). Voxel grids are streamed.",
    )
    p.add_argument("map")
    p.add_argument("-o", "--output", required=True, help="map file to write")
    p.add_argument("--max-landmarks", type=int, metavar="N", help="landmark budget")
    p.add_argument("--min-track", type=int, metavar="K", help="keep landmarks seen in at least K frames")
    p.add_argument("--min-quality", type=float, metavar="Q", help="keep landmarks with training PSNR >= Q dB")
    p.add_argument("--bbox", metavar="x0,y0,z0,x1,y1,z1", help="keep landmarks inside this axis-aligned box")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_threads_arg(p)
    add_rerun_args(p)
    p.set_defaults(func=run)
    p._negative_number_matcher = re.compile(r"^-\.?\d")  # '--bbox -1,-2,...' is a value, not an option


def run(args) -> int:
    from ..errors import InputError
    from ..ops.prune import parse_bbox, prune_map, reason_text

    if args.max_landmarks is not None and args.max_landmarks < 1:
        raise InputError(f"--max-landmarks must be >= 1, got {args.max_landmarks}")
    if args.min_track is not None and args.min_track < 1:
        raise InputError(f"--min-track must be >= 1, got {args.min_track}")
    bbox = parse_bbox(args.bbox) if args.bbox is not None else None
    rec = recording_from_args(args, "favormap prune")
    bars = StageBars(args.quiet or args.json)
    try:
        res = prune_map(
            args.map, args.output, args.max_landmarks, args.min_track, args.min_quality, bbox, progress=bars
        )
    finally:
        bars.close()
    if rec is not None:
        rec.log_prune(args.map, args.output)
        rec.close()
    d = res.to_dict()
    d["file_size"] = Path(args.output).stat().st_size
    if args.json:
        print_json(d)
        return 0
    print(f"kept                {res.num_after} of {res.num_before} landmarks")
    for k, v in res.removed.items():
        also = res.failing.get(k, v) - v
        print(
            f"removed {v:>7}     {reason_text(k, res)}"
            + (f"  ({also} more fail this test but were already removed above)" if also else "")
        )
    print(f"file                {args.output}  ({human_size(d['file_size'])})")
    return 0
