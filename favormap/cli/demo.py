"""favormap demo: synthetic room -> map -> localize held-out views. Needs no data."""

from __future__ import annotations

from pathlib import Path

from ..threads import add_threads_arg
from .common import StageBars, auto_device


def register(sub):
    p = sub.add_parser(
        "demo",
        help="build a map of a synthetic room and localize held-out views (no data needed)",
        description="Render a textured synthetic room along a camera path (Open3D raycasting), build a "
        "map from 4 of every 5 frames, then localize the held-out frames from priors "
        "perturbed by --noise and print the errors.",
    )
    p.add_argument(
        "--workdir",
        default="favormap-demo",
        help="where the rendered sequence and the map are written and kept (default ./favormap-demo)",
    )
    p.add_argument("--frames", type=int, default=30, help="frames rendered (default 30)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--noise", default="0.3,15", help="prior perturbation 'T_UNITS,DEG' (default 0.3,15)")
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="train the voxels with Adam (--quality fast) for this many iterations (default: the build's defaults)",
    )
    p.add_argument(
        "--exact-poses",
        action="store_true",
        help="build as `favormap build --exact-poses` does (the room's poses are exact): tracks and query keypoints "
        "aligned to the mapping images",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto")
    add_threads_arg(p)
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..build import BuildConfig, build_map
    from ..errors import InputError
    from ..localize import LocalizeConfig, Localizer
    from ..localize.evaluate import EvalConfig, evaluate, format_table
    from ..mapfile import write_map
    from ..synthetic import write_sequence
    from ..voxels import VoxelConfig
    from .build import print_summary, summary
    from .eval import parse_noise

    if args.frames < 10:
        raise InputError("--frames must be >= 10")
    if args.iterations is not None and args.iterations < 1:
        raise InputError("--iterations must be >= 1")
    noise = parse_noise(args.noise)
    device = auto_device(args.device)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    print(f"rendering a synthetic room: {args.frames} frames {args.width}x{args.height} -> {work / 'room'}")
    seq = write_sequence(work / "room", n_frames=args.frames, width=args.width, height=args.height, seed=args.seed)
    held = [i for i in range(len(seq)) if i % 5 == 2]
    train = [i for i in range(len(seq)) if i % 5 != 2]
    # the build's defaults; --iterations: Adam training ("fast") with that many iterations
    cfg = BuildConfig(exact_poses=args.exact_poses)
    if args.iterations is not None:
        cfg.voxel = VoxelConfig.preset("fast", iterations=args.iterations)
    bars = StageBars(args.quiet)
    try:
        m = build_map(seq.subset(train), cfg, progress=bars, device=device)
    finally:
        bars.close()
    path = work / "room.h5"
    write_map(m, path)
    print(f"\nmap built from {len(train)} frames:")
    print_summary(summary(m, path))
    print(f"\nlocalizing {len(held)} held-out frames from priors moved by {noise[0]} units / {noise[1]} deg:")
    locs = {name: Localizer(path, LocalizeConfig(device=device, descriptors=name)) for name in ("rendered", "mean")}
    try:
        reports = evaluate(locs, seq.subset(held), EvalConfig(noise=noise, seed=args.seed))
    finally:
        for loc in locs.values():
            loc.close()
    print(format_table(reports))
    print(f"\nkept: sequence {work / 'room'}, map {path}  (try: favormap info {path})")
    return 0
