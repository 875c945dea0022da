"""favormap info map.h5 [--json]"""

from __future__ import annotations

from .common import estimated_poses_line, human_size, print_json, reproj_error_line, voxel_memory_line


def register(sub):
    p = sub.add_parser("info", help="describe a map", description="Print a map's metadata and statistics.")
    p.add_argument("map")
    p.add_argument("--json", action="store_true", help="one JSON object")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..mapfile import Map

    with Map.open(args.map) as m:
        info = m.info()
    if args.json:
        print_json(info)
        return 0
    print(
        f"{info['path']}: favormap map v{info['format_version']} (favormap {info['favormap_version']}, created "
        f"{info['created']})"
    )
    print(f"landmarks           {info['num_landmarks']}")
    print(f"frames / cameras    {info['num_frames']} / {info['num_cameras']}")
    print(f"extractor           {info['extractor']} ({info['channels']} channels)")
    print(
        f"grid / patch        R={info['grid_resolution']} / S={info['patch_size']}  (render samples "
        f"{info['render_samples']}, images max side {info['max_side']})"
    )
    if info["num_landmarks"]:
        print(f"mean track length   {info['mean_track_length']:.2f}")
        print(reproj_error_line(info["median_reproj_error_px"]))
        print(f"median PSNR         {info['median_psnr']:.2f} dB")
        lo, hi = info["bbox"]
        print("bounding box        " + " .. ".join("(" + ", ".join(f"{v:.3f}" for v in c) + ")" for c in (lo, hi)))
    if info["align_patches"]:
        r = info["align_patches"]
        print(f"observation patches {2 * r + 1} x {2 * r + 1} px (localize --align needs no mapping images)")
    if info["aligns_by_default"]:
        why = "built with --exact-poses" if info["exact_poses"] else f"{info['extractor']} keypoints"
        print(f"keypoint alignment  on by default in localize ({why}; --no-align turns it off)")
    if info["camera_rotation_deg"]:
        print(
            f"camera rotation     {info['camera_rotation_deg']:.2f} deg against the poses the map was built from "
            "(frames/cam_from_rig): localize takes and reports poses in their frame"
        )
    if info["estimated_poses"]:
        print(estimated_poses_line(info["estimated_poses"]))
    print(f"file size           {human_size(info['file_size'])}")
    print(voxel_memory_line(info["voxel_memory_bytes"]))
    return 0
