"""favormap export map.h5 -o landmarks.ply|.glb|.obj [--boxes] [--color quality|track]"""

from __future__ import annotations

from .common import human_size, print_json


def register(sub):
    p = sub.add_parser(
        "export",
        help="export landmarks (and voxel boxes) as .ply/.glb/.obj",
        description="Write the landmarks as a coloured point cloud (by training PSNR or track length); "
        "--boxes adds one cube per landmark with its voxel size (.glb: points and boxes; "
        ".ply/.obj: the boxes only).",
    )
    p.add_argument("map")
    p.add_argument("-o", "--output", required=True, help="output file: .ply, .glb or .obj")
    p.add_argument("--boxes", action="store_true", help="one box per landmark, its voxel size")
    p.add_argument(
        "--color", choices=("quality", "track"), default="quality", help="colour by PSNR (default) or track length"
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from ..ops.export import export_landmarks

    res = export_landmarks(args.map, args.output, boxes=args.boxes, color_by=args.color)
    d = res.to_dict()
    d["file_size"] = Path(args.output).stat().st_size
    if args.json:
        print_json(d)
        return 0
    lo, hi = res.value_range
    unit = " dB" if res.color_by == "quality" else " frames"
    parts = []
    if res.num_points:
        parts.append(f"{res.num_points} landmarks")
    if res.num_boxes:
        parts.append(f"{res.num_boxes} boxes")
    print(
        f"wrote {args.output}: {' + '.join(parts)}, coloured by {res.color_by} ({lo:.1f}..{hi:.1f}{unit})  "
        f"({human_size(d['file_size'])})"
    )
    return 0
