"""favormap merge a.h5 b.h5 [c.h5 ...] -o merged.h5 [--dedup-radius R] [--transform b_to_a.txt | --align]"""

from __future__ import annotations

import sys
from pathlib import Path

from ..ops.merge_config import MergeConfig
from ..threads import add_threads_arg
from ..viz import add_rerun_args, recording_from_args
from .align import add_align_args, align_config, print_warnings, summary_lines
from .common import StageBars, config_default, human_size, print_json


def register(sub):
    p = sub.add_parser(
        "merge",
        help="merge maps into one",
        description="Merge maps built with the same extractor, channels, grid and patch size. Landmarks "
        "of later maps that duplicate an existing one (closer than the dedup radius, mean "
        "descriptor cosine > --min-cosine) keep only the better (higher PSNR) one; frames, "
        "cameras and tracks are concatenated. Voxel grids are streamed.",
    )
    p.add_argument("maps", nargs="+", help="two or more map files; the first defines the frame")
    p.add_argument("-o", "--output", required=True, help="merged map file to write")
    p.add_argument(
        "--dedup-radius",
        type=float,
        metavar="R",
        help="duplicate distance (default: the existing landmark's voxel size)",
    )
    p.add_argument(
        "--min-cosine",
        type=float,
        default=config_default(MergeConfig, "min_cosine"),
        help="mean-descriptor cosine above which close landmarks are duplicates (default %(default)s)",
    )
    p.add_argument("--no-dedup", action="store_true", help="keep every landmark")
    p.add_argument(
        "--transform",
        metavar="FILE",
        help="4x4 b_to_a matrix (rigid or similarity) applied to the second and later maps",
    )
    p.add_argument(
        "--align",
        action="store_true",
        help="estimate b_to_a from the landmarks first (as 'favormap align'; two maps only)",
    )
    add_align_args(p)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_threads_arg(p)
    add_rerun_args(p)
    p.set_defaults(func=run)


def merge_config(args) -> MergeConfig:
    return MergeConfig(dedup=not args.no_dedup, dedup_radius=args.dedup_radius, min_cosine=args.min_cosine)


def run(args) -> int:
    from ..errors import InputError
    from ..io.posefile import read_transform
    from ..ops.merge import merge_maps

    if len(args.maps) < 2:
        raise InputError("merge needs at least two maps")
    T = read_transform(args.transform)[0] if args.transform else None
    alignment = None
    if args.align:
        from ..mapfile.writer import check_output_path
        from ..ops.align import align_maps

        if args.transform:
            raise InputError("--align and --transform exclude each other")
        if len(args.maps) != 2:
            raise InputError(f"--align takes exactly two maps, got {len(args.maps)}")
        check_output_path(args.output, args.maps)  # fail before any work
        alignment = align_maps(args.maps[0], args.maps[1], align_config(args))
        T = alignment.b_to_a
        if not args.json:
            for line in summary_lines(alignment):
                print(line)
        print_warnings("merge", alignment.warnings)
    rec = recording_from_args(args, "favormap merge")
    bars = StageBars(args.quiet or args.json)
    try:
        res = merge_maps(
            args.maps,
            args.output,
            merge_config(args),
            transform=T,
            progress=bars,
        )
    finally:
        bars.close()
    if rec is not None:
        rec.log_merge(args.maps, args.output)
        rec.close()
    for w in res.warnings:
        print(f"favormap merge: warning: {w}", file=sys.stderr)
    d = res.to_dict()
    d["file_size"] = Path(args.output).stat().st_size
    if alignment is not None:
        d["alignment"] = alignment.to_dict()
    if args.json:
        print_json(d)
        return 0
    for s in res.sources:
        print(
            f"{s['path']}: {s['landmarks']} landmarks, {s['in_output']} in the merged map"
            + (
                f" ({s['dropped_duplicates']} duplicates dropped, {s['replaced']} replaced a worse duplicate)"
                if s["dropped_duplicates"] or s["replaced"]
                else ""
            )
        )
    cams = f"{res.num_cameras} camera" + ("s" if res.num_cameras != 1 else "")
    print(
        f"merged              {res.num_landmarks} landmarks, {res.num_frames} frames, {cams}"
        + (f", {res.ids_regenerated} colliding ids regenerated" if res.ids_regenerated else "")
    )
    print(f"file                {args.output}  ({human_size(d['file_size'])})")
    return 0
