"""favormap view map.h5 [--rerun-save FILE.rrd | --rerun-connect URL]"""

from __future__ import annotations

from ..viz import add_rerun_args, recording_from_args, rerun_requested


def register(sub):
    p = sub.add_parser(
        "view",
        help="open a map in the rerun viewer",
        description="Show a map in rerun: landmarks (coloured by track length or quality), their voxel "
        "boxes coloured by quality (PSNR), and the mapping camera path with frustums. "
        "Spawns a viewer unless --rerun-save or --rerun-connect is given. Entity paths: "
        "docs/rerun.md.",
    )
    p.add_argument("map")
    p.add_argument(
        "--color-by",
        choices=["track_length", "quality"],
        default="track_length",
        help="landmark colours (default track_length; voxels are always coloured by quality)",
    )
    p.add_argument("--no-voxels", action="store_true", help="landmarks and cameras only")
    add_rerun_args(p, spawn_by_default=True)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..mapfile import Map

    with Map.open(args.map) as m:
        rec = recording_from_args(args, "favormap view", spawn=not rerun_requested(args))
        ok = False
        try:
            rec.log_map(m, voxels=not args.no_voxels, color_by=args.color_by)
        finally:
            ok = rec.close()
    where = ", ".join(
        w for w in (args.rerun_save, args.rerun_connect, "the rerun viewer" if rec.spawned else None) if w
    )
    print(
        f"{args.map}: {len(m)} landmarks, {m.num_frames} frames -> {where}" + ("" if ok else " (not fully delivered)")
    )
    return 0 if ok else 1
