"""favormap pose --from KIND SOURCE [--name NAME] [-o prior.txt]: write a prior from another tool's pose."""

from __future__ import annotations

import sys

# the forms a pose can be given in (favormap.io.posefile.convert_pose reads each); here so that --help
# imports nothing heavy
SOURCES = {
    "world_from_cam": "a 4x4 (or 3x4) camera-to-world matrix in OpenCV axes, or a TUM line (what --prior reads)",
    "cam_from_world": "a 4x4 (or 3x4) world-to-camera matrix in OpenCV axes (COLMAP's, OpenCV's solvePnP)",
    "opengl": (
        "a 4x4 camera-to-world matrix in OpenGL axes (x right, y up, z backward: NeRF, Blender, LLFF after reordering)"
    ),
    "nerf": "transforms.json with --name: the transform_matrix of the frame whose file_path matches",
    "colmap": "a COLMAP images.txt line 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME' (or the 7 numbers "
    "QW QX QY QZ TX TY TZ), or images.txt with --name",
    "tum": (
        "a TUM line 'timestamp tx ty tz qx qy qz qw' (or without the timestamp), or groundtruth.txt with --name "
        "TIMESTAMP (the nearest line)"
    ),
    "7scenes": "a 7-Scenes frame-NNNNNN.pose.txt (camera-to-world, OpenCV axes)",
}


def register(sub):
    kinds = "; ".join(f"{k}: {v}" for k, v in SOURCES.items())
    p = sub.add_parser(
        "pose",
        help="convert a pose from another tool into a prior file (world_from_cam)",
        description="Write the prior that `localize --prior` reads (a 4x4 world_from_cam matrix, OpenCV "
        "axes) from a pose in another tool's form. Sources: " + kinds,
    )
    p.add_argument(
        "source",
        help="a file, the pose text itself (quote it), or a sequence folder with --name (nerf: its transforms.json, "
        "colmap: its model, binary too, tum: its groundtruth.txt, 7scenes: the frame's NAME.pose.txt)",
    )
    p.add_argument("--from", dest="kind", required=True, choices=list(SOURCES), help="the form of SOURCE")
    p.add_argument("--name", help="which pose of a file: a NeRF file_path, a COLMAP image name, a TUM timestamp")
    p.add_argument("-o", "--output", help="prior file to write (default: print it)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from ..geometry import inverse
    from ..io.posefile import convert_pose, write_pose

    cam_from_world = convert_pose(args.kind, args.source, args.name)
    if args.output:
        from ..mapfile.writer import atomic_path, check_output_path

        out = check_output_path(
            args.output, [args.source] if len(args.source) < 1024 and "\n" not in args.source else []
        )
        with atomic_path(out) as tmp:
            write_pose(tmp, cam_from_world)
        print(f"wrote {out} (world_from_cam, OpenCV axes): localize --prior {out}")
    else:
        np.savetxt(sys.stdout, inverse(cam_from_world), fmt="%.12g")
    return 0
