"""favormap query map.h5 --pose pose.txt [--camera CAM] [--mesh mesh.ply] [--json]
favormap query map.h5 --near X Y Z (--radius R | --knn K) [--json]"""

from __future__ import annotations

import re
import sys

from ..threads import add_threads_arg
from ..view_limits import ViewLimits
from .common import config_default, print_json

_LIMIT = {name: config_default(ViewLimits, name) for name in ("angle_margin_deg", "depth_scale", "image_margin_px")}


def register(sub):
    p = sub.add_parser(
        "query",
        help="landmarks visible from a pose, or near a point",
        description="List the landmarks visible from a camera pose (frustum, the depth and viewing-angle "
        "ranges each landmark was trained for, optionally not occluded by a mesh), or the "
        "landmarks near a point. Exit status 1 when nothing is found.",
    )
    p.add_argument("map")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument(
        "--pose",
        metavar="FILE",
        help="world_from_cam pose file: 4x4 (or 3x4) matrix text, or one TUM line 'tx ty tz qx qy qz qw'",
    )
    g.add_argument("--near", nargs=3, type=float, metavar=("X", "Y", "Z"), help="a point in map coordinates")
    p.add_argument(
        "--camera",
        metavar="CAM",
        help="query camera: COLMAP cameras.txt line ('MODEL W H params...'), JSON, or a file "
        "with either (default: the map's first camera)",
    )
    p.add_argument("--mesh", metavar="MESH", help="scene mesh (any format trimesh reads): drop landmarks it occludes")
    p.add_argument("--radius", type=float, help="with --near: landmarks within this distance")
    p.add_argument("--knn", type=int, metavar="K", help="with --near: the K nearest landmarks")
    p.add_argument(
        "--angle-margin",
        type=float,
        default=_LIMIT["angle_margin_deg"],
        metavar="DEG",
        help="allowed viewing angle beyond each landmark's training range (default %(default)s)",
    )
    p.add_argument(
        "--depth-scale",
        type=float,
        nargs=2,
        default=_LIMIT["depth_scale"],
        metavar=("LO", "HI"),
        help="allowed distance range relative to each landmark's training range (default "
        + " ".join(f"{v:g}" for v in _LIMIT["depth_scale"])
        + ")",
    )
    p.add_argument(
        "--margin",
        type=float,
        default=_LIMIT["image_margin_px"],
        metavar="PX",
        help="keep landmarks at least this far inside the image (default %(default)s)",
    )
    p.add_argument("--limit", type=int, default=20, help="landmarks listed in the human output (default 20; 0: all)")
    p.add_argument("--json", action="store_true", help="one JSON object (visible_ids / ids, counts)")
    add_threads_arg(p)
    p.set_defaults(func=run)
    p._negative_number_matcher = re.compile(r"^-\.?\d")  # '--near -1e-3 2 3' are values, not options


def _load_mesh(path):
    from pathlib import Path

    import trimesh

    from ..errors import InputError, first_line

    path = Path(path)
    if not path.is_file():
        raise InputError(f"mesh not found: {path}")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as e:  # noqa: BLE001 - trimesh raises many types
        raise InputError(f"cannot read mesh {path}: {type(e).__name__}: {first_line(e)}") from None
    if len(getattr(mesh, "faces", [])) == 0:
        raise InputError(f"mesh {path} has no triangles")
    return mesh


def view_limits(args) -> ViewLimits:
    return ViewLimits(args.angle_margin, tuple(args.depth_scale), args.margin)


def run(args) -> int:
    import numpy as np

    from ..errors import InputError
    from ..io.posefile import read_camera, read_pose
    from ..mapfile import Map
    from ..ops.query import query_near, query_pose

    if args.near is not None:
        if args.camera or args.mesh:
            raise InputError("--camera and --mesh go with --pose, not --near")
        if (args.radius is None) == (args.knn is None):
            raise InputError("--near needs exactly one of --radius R or --knn K")
    elif args.radius is not None or args.knn is not None:
        raise InputError("--radius and --knn go with --near")
    limits = view_limits(args)
    lo, hi = limits.depth_scale
    if not (0 <= lo <= hi) or not np.isfinite(hi) or args.angle_margin < 0 or args.margin < 0:
        raise InputError("--depth-scale needs 0 <= LO <= HI; --angle-margin and --margin must be >= 0")
    pose = read_pose(args.pose) if args.pose else None
    camera = read_camera(args.camera) if args.camera else None
    mesh = _load_mesh(args.mesh) if args.mesh else None
    with Map.open(args.map) as m:
        if pose is not None:
            res = query_pose(m, pose, camera, mesh, limits)
        else:
            res = query_near(m, args.near, args.radius, args.knn)
        positions = m.positions[res.rows]
        quality = m.quality[res.rows]
    d = {"map": args.map, **res.to_dict()}
    if args.json:
        print_json(d)
    else:
        _print_human(res, d, positions, quality, args.limit)
    if len(res.rows) == 0:
        what = "no landmark is visible from this pose" if res.mode == "pose" else "no landmark found near this point"
        print(f"favormap query: {what}", file=sys.stderr)
        return 1
    return 0


def _print_human(res, d, positions, quality, limit):
    import numpy as np

    if res.mode == "pose":
        print(f"visible             {d['num_visible']} of {d['num_landmarks']} landmarks")
        print(
            f"in frustum          {d['num_in_frustum']}  (within trained depth/angle: {d['num_view_ok']}, occluded: "
            f"{d['num_occluded']})"
        )
        c = res.camera
        print(
            f"camera              {c.model} {c.width}x{c.height}  centre in world ("
            + ", ".join(f"{v:.3f}" for v in res.camera_center)
            + ") scene units"
        )
        dist = np.linalg.norm(positions - res.camera_center, axis=1)
    else:
        print(f"found               {d['count']} of {d['num_landmarks']} landmarks")
        dist = res.distances
    n = len(res.rows) if limit <= 0 else min(limit, len(res.rows))
    if n:
        print("positions and distances in scene units, training PSNR in dB")
        print(f"{'id':>20} {'row':>8} {'x':>9} {'y':>9} {'z':>9} {'dist':>8} {'PSNR dB':>7}")
        for i in range(n):
            x, y, z = positions[i]
            print(
                f"{int(res.ids[i]):>20} {int(res.rows[i]):>8} {x:9.3f} {y:9.3f} {z:9.3f} {dist[i]:8.3f} "
                f"{quality[i]:7.1f}"
            )
        if n < len(res.rows):
            print(f"... {len(res.rows) - n} more (--limit 0 lists all, --json prints every id)")
