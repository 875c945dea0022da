"""favormap build of images without poses: a folder of photos or a video, posed by pycolmap first
(:mod:`favormap.io.sfm`), then built as any posed sequence."""

from __future__ import annotations

from pathlib import Path

VIDEO_MOTION = 0.05  # the default of io.video.extract_frames (not imported here: the CLI starts without OpenCV)


def add_sfm_args(p, scale: bool = True, then: str = "the build") -> None:
    """The options of images without poses; ``scale``: with --scale (a build; extend takes the map's units)."""
    g = p.add_argument_group(
        "images without poses",
        "a folder of images in no sequence format, or a video file, is posed by structure from motion (COLMAP's "
        f"incremental mapper, through pycolmap) before {then}; the reconstruction is kept in COLMAP's layout",
    )
    g.add_argument(
        "--sfm-dir",
        metavar="DIR",
        help="where the reconstruction goes (COLMAP's database.db and sparse/0; default: OUTPUT.sfm next to the "
        "map written)",
    )
    g.add_argument(
        "--matcher",
        choices=("auto", "sequential", "exhaustive"),
        default="auto",
        help="which image pairs are matched: sequential (each image with its next 10, for video and ordered "
        "captures), exhaustive (every pair, for small unordered sets) or auto (default: sequential for a video "
        "or more than 60 images, exhaustive otherwise)",
    )
    g.add_argument(
        "--camera",
        metavar="CAM",
        help="the images' camera, known: a COLMAP camera line 'MODEL W H params...', JSON, or a file holding "
        "either (default: estimated, one camera for all images)",
    )
    g.add_argument("--camera-per-image", action="store_true", help="estimate one camera for each image")
    if scale:
        g.add_argument(
            "--scale",
            type=float,
            metavar="S",
            help="multiply the reconstruction's units by S (e.g. metres per unit, measured between two known "
            "points); without it the map's units are arbitrary",
        )
        g.add_argument(
            "--anchor-poses",
            metavar="FILE",
            help="known poses of 3 or more of the images, not on one line (GPS/RTK, motion capture, a surveyed "
            "tripod): lines 'IMAGE_NAME tx ty tz qx qy qz qw' or 'IMAGE_NAME' + 16 numbers (world_from_cam, "
            "row-major); the reconstruction is moved into their frame and units by the similarity that best fits "
            "its camera centres to theirs (instead of --scale)",
        )
    g.add_argument(
        "--video-every",
        type=int,
        default=0,
        metavar="N",
        help="video: keep one frame in N (default: keep a frame when the view has moved, see --video-motion)",
    )
    g.add_argument(
        "--video-motion",
        type=float,
        default=VIDEO_MOTION,
        metavar="F",
        help="video: keep a frame when tracked corners have moved F times the image width since the last kept "
        "one (median; default %(default)s)",
    )


def unposed_kind(path) -> str | None:
    """What ``path`` holds: "video", "images" (a folder of images in no sequence format) or None (a sequence)."""
    from ..io import detect_format_or_none
    from ..io.sfm import list_images
    from ..io.video import is_video

    path = Path(path)
    if is_video(path):
        return "video"
    if path.is_dir() and detect_format_or_none(path) is None and list_images(path):
        return "images"
    return None


def _check_args(args, kind: str | None) -> None:
    from ..errors import InputError

    sfm_only = ("sfm_dir", "camera", "scale", "anchor_poses")
    if kind is None:
        given = [n for n in sfm_only if getattr(args, n, None) is not None]
        given += [n for n in ("camera_per_image",) if getattr(args, n)] + (
            ["matcher"] if args.matcher != "auto" else []
        )
        if given:
            raise InputError(
                f"--{given[0].replace('_', '-')} applies to images without poses (a folder of images in no sequence "
                f"format, or a video), not to {args.sequence}"
            )
    if getattr(args, "scale", None) is not None and getattr(args, "anchor_poses", None) is not None:
        raise InputError("--anchor-poses and --scale exclude each other: the anchors' poses set the scale")
    if kind != "video" and (args.video_every or args.video_motion != VIDEO_MOTION):
        raise InputError(f"--video-every and --video-motion apply to a video, not to {args.sequence}")
    if args.video_every < 0:
        raise InputError(f"--video-every must be >= 1 (or 0: by motion), not {args.video_every}")
    if not 0 < args.video_motion < 1:
        raise InputError(f"--video-motion must be in (0, 1), not {args.video_motion}")


def _kept(names: list[str], every: int) -> list[str]:
    """``build --exclude-every``: frames 0, N, 2N, ... left out (before the poses are estimated)."""
    return [n for i, n in enumerate(names) if not every or i % every]


def estimate_poses_from_args(args, out: Path, progress):
    """The SfmResult of an unposed input (its poses estimated here), or None for a posed sequence."""
    from ..io.posefile import read_camera
    from ..io.sfm import SfmOptions, check_output, default_output, estimate_poses, list_images
    from ..io.video import extract_frames
    from .queries import read_priors

    kind = None if getattr(args, "format", None) else unposed_kind(args.sequence)  # --format: a posed sequence
    _check_args(args, kind)
    if kind is None:
        return None
    sfm_dir = check_output(Path(args.sfm_dir) if args.sfm_dir else default_output(out))
    opts = SfmOptions(
        matcher=args.matcher,
        camera=read_camera(args.camera) if args.camera else None,
        camera_per_image=args.camera_per_image,
        scale=getattr(args, "scale", None),
        anchors=read_priors(Path(args.anchor_poses), "anchor poses") if getattr(args, "anchor_poses", None) else None,
        threads=getattr(args, "threads", None),
        ordered=kind == "video",
    )
    every = getattr(args, "exclude_every", 0)
    if kind == "images":
        opts.image_names = _kept(list_images(args.sequence), every)
        return estimate_poses(args.sequence, sfm_dir, opts, progress)

    def frames(work: Path):
        v = extract_frames(args.sequence, work / "images", args.video_every, args.video_motion, progress)
        return v.folder, _kept(v.names, every)

    return estimate_poses(None, sfm_dir, opts, progress, prepare=frames)


def print_sfm_summary(p: dict, units: bool = True) -> None:
    """The summary's lines of the estimated poses (``SfmResult.to_dict()``); ``units``: say the map's units (a
    build; an extension keeps the map's)."""
    from .common import estimated_poses_line

    total = p["registered"] + len(p["unregistered"])
    print(estimated_poses_line(p, units))
    print(
        f"registered          {p['registered']} of {total} frames  (mean reprojection error "
        f"{p['mean_reprojection_error_px']:.2f} px, {p['points']} points, {p['seconds']:.1f} s)"
    )
    if p["unregistered"]:
        print(f"not registered      {len(p['unregistered'])}: {', '.join(p['unregistered'])}")
    if p["models"] > 1:
        others = ", ".join(str(n) for n in p["other_models_registered"])
        print(f"models              {p['models']}: the largest used; the others posed {others} frames (sparse/1, ...)")
    if p.get("anchors"):
        print_anchors_summary(p["anchors"])
    print(f"reconstruction      {p['reconstruction']}  (COLMAP model; images in {p['image_dir']})")


def print_anchors_summary(a: dict) -> None:
    """The summary's lines of the fit to the anchor poses (``AnchorFit.to_dict()``)."""
    print(
        f"anchors             {a['anchors']} images: scale {a['scale']:.6g}; camera centres off by "
        f"{a['residual_rms']:.3g} m RMS, {a['residual_max']:.3g} m max, turned {a['rotation_median_deg']:.2f} deg "
        "(median) from the anchors' orientations"
    )
    if a["missing"]:
        print(f"anchors not used    {len(a['missing'])} name no image: {', '.join(a['missing'])}")
    if a["unregistered"]:
        print(f"anchors not used    {len(a['unregistered'])} not registered: {', '.join(a['unregistered'])}")
