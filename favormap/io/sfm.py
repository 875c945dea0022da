"""Poses of images that have none: structure from motion with pycolmap (COLMAP's pipeline).

SIFT features are extracted from every image into a COLMAP database, matched (``sequential``: each
image with the images that follow it, for video and ordered captures; ``exhaustive``: every pair,
for small unordered sets; ``auto``: exhaustive up to ``EXHAUSTIVE_MAX`` images, sequential above),
and COLMAP's incremental mapper poses the images it can; an estimated camera shared by all images is then
refined once more with its principal point (:func:`refine_camera`). The reconstruction is written in COLMAP's
layout to a folder of its own, so that COLMAP's GUI opens it::

    DIR/database.db            features and matches
    DIR/sparse/0/              the model the poses come from (the largest, when there are several)
    DIR/sparse/1/ ...          the other models, largest first
    DIR/images/                the frames of a video (a folder of photos stays where it is)
    DIR/favormap-sfm.json      what was done: matcher, registered and unregistered images, ...

The folder is written under a temporary name and renamed into place when complete. Its units and
world frame are arbitrary (COLMAP's), unless ``scale`` gives a factor to multiply them by, or ``anchors``
give the known poses of a few images: the model used is then moved into their frame and units by the
similarity that fits its camera centres to theirs (:mod:`.sfm_anchors`; the other models stay as they are).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FavormapError, InputError, first_line
from ..geometry import from_rigid3d
from .sfm_anchors import anchor_reconstruction, check_anchors
from .types import SUPPORTED_MODELS, Camera, Frame, Sequence

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
MATCHERS = ("auto", "sequential", "exhaustive")
EXHAUSTIVE_MAX = 60  # auto: every pair up to this many images (~1,800 pairs), the next SEQUENTIAL_OVERLAP above
SEQUENTIAL_OVERLAP = 10
MARKER = "favormap-sfm.json"
FORMAT = "sfm"  # Sequence.format of the estimated sequences


class PosesNotFound(FavormapError):
    """Pose estimation that posed no image (too little overlap or texture)."""


@dataclass
class SfmOptions:
    """How the poses are estimated. ``camera``: known intrinsics (held fixed), else estimated, one camera
    for all images unless ``camera_per_image``. ``image_names``: the images of the folder to use (default:
    every image, in name order). ``scale``: multiplies the reconstruction's units (None: arbitrary).
    ``anchors``: {image name (or name without extension): cam_from_world} of images whose poses are known,
    3 or more, not on one line: the reconstruction is moved into their frame (instead of ``scale``)."""

    matcher: str = "auto"
    camera: Camera | None = None
    camera_per_image: bool = False
    image_names: list[str] | None = None
    max_image_size: int = 1600
    max_features: int = 8192
    scale: float | None = None
    threads: int | None = None
    seed: int = 0
    ordered: bool = False  # the images are frames of a video: auto matches sequentially
    anchors: dict | None = None

    def __post_init__(self):
        if self.matcher not in MATCHERS:
            raise InputError(f"unknown matcher {self.matcher!r} (choose from {', '.join(MATCHERS)})")
        if self.scale is not None and not (np.isfinite(self.scale) and self.scale > 0):
            raise InputError(f"the scale must be a positive number, not {self.scale}")
        if self.scale is not None and self.anchors is not None:
            raise InputError("a scale and anchor poses exclude each other: the anchors' poses set the scale")
        if self.camera is not None and self.camera_per_image:
            raise InputError("a given camera is shared by all images; it cannot go with one camera per image")

    def resolved_matcher(self, n_images: int) -> str:
        if self.matcher != "auto":
            return self.matcher
        return "sequential" if self.ordered or n_images > EXHAUSTIVE_MAX else "exhaustive"


@dataclass
class SfmResult:
    """Stage boundary: the estimated poses as a Sequence and what the estimation did."""

    sequence: Sequence  # the registered images, posed, in name order
    reconstruction_path: Path  # DIR/sparse/0
    image_dir: Path
    registered: list[str]
    unregistered: list[str]
    mean_reprojection_error_px: float
    mapper: str  # "incremental"
    matcher: str  # "sequential" or "exhaustive"
    num_models: int
    num_points: int
    scale: float | None
    seconds: float
    other_models: list[int] = field(default_factory=list)  # registered images of the models not used
    camera_refined: bool = False  # the final adjustment of the camera kept (refine_camera)
    anchors: dict | None = None  # the fit to the anchor poses (sfm_anchors.AnchorFit.to_dict()), if given

    @property
    def units(self) -> str:
        if self.anchors is not None:
            return "anchors"
        return "arbitrary" if self.scale is None else "scaled"

    def to_dict(self) -> dict:
        """The provenance of the poses (stored in the map and in DIR/favormap-sfm.json)."""
        return {
            "source": "sfm",
            "reconstruction": str(self.reconstruction_path),
            "image_dir": str(self.image_dir),
            "mapper": self.mapper,
            "matcher": self.matcher,
            "registered": len(self.registered),
            "unregistered": list(self.unregistered),
            "mean_reprojection_error_px": round(self.mean_reprojection_error_px, 4),
            "points": self.num_points,
            "models": self.num_models,
            "other_models_registered": list(self.other_models),
            "camera_refined": self.camera_refined,
            "units": self.units,
            "scale": self.scale,
            **({"anchors": dict(self.anchors)} if self.anchors is not None else {}),
            "seconds": round(self.seconds, 2),
        }


def list_images(folder) -> list[str]:
    """The image files directly in ``folder``, in name order."""
    folder = Path(folder)
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def default_output(map_path) -> Path:
    """Where the reconstruction of a map goes unless named: next to it, ``MAP.sfm``."""
    p = Path(map_path)
    return p.with_name(p.name + ".sfm")


def check_output(out) -> Path:
    """``out`` may be written: absent, empty, or an earlier reconstruction of favormap (replaced)."""
    out = Path(out)
    if out.exists() and not (out.is_dir() and (not any(out.iterdir()) or (out / MARKER).is_file())):
        raise InputError(f"{out} exists and is not a reconstruction of favormap; name another folder for it")
    return out


def _check_camera(camera: Camera | None, image: Path) -> None:
    """A given camera must have the images' size (COLMAP would take its parameters at the wrong scale)."""
    if camera is None:
        return
    import cv2

    im = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if im is None:
        raise InputError(f"cannot read the image {image}")
    h, w = im.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(f"the camera is {camera.width}x{camera.height} but the images are {w}x{h} ({image.name})")


def _pycolmap_options(opts: SfmOptions):
    import pycolmap

    threads = -1 if opts.threads is None else int(opts.threads)
    reader = pycolmap.ImageReaderOptions()
    if opts.camera is not None:
        reader.camera_model = opts.camera.model
        reader.camera_params = ",".join(f"{v:.17g}" for v in opts.camera.params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(opts.max_image_size)
    extraction.sift.max_num_features = int(opts.max_features)
    extraction.num_threads = threads
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.random_seed = int(opts.seed)
    if opts.camera is not None:  # known intrinsics stay as given
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
    mode = pycolmap.CameraMode.PER_IMAGE if opts.camera_per_image else pycolmap.CameraMode.SINGLE
    return reader, extraction, matching, mapping, mode


def _match(db: Path, matcher: str, matching) -> None:
    import pycolmap

    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)


def _reconstruct(image_dir: Path, names: list[str], work: Path, opts: SfmOptions, matcher: str, report) -> list:
    """COLMAP's features, matches and incremental models of ``names`` in ``work``: the models, largest first."""
    import pycolmap

    from ..pose_refinement import quiet_colmap

    reader, extraction, matching, mapping, mode = _pycolmap_options(opts)
    db = work / "database.db"
    registered = [0]

    def next_image():
        registered[0] += 1
        report("sfm poses", min(registered[0], len(names)), len(names))

    with quiet_colmap("FATAL"):  # what fails is told by the result (PosesNotFound, unregistered images)
        report("sfm features", 0, 1)
        pycolmap.extract_features(db, image_dir, names, mode, reader, extraction, device=pycolmap.Device.cpu)
        report("sfm features", 1, 1)
        report("sfm matches", 0, 1)
        _match(db, matcher, matching)
        report("sfm matches", 1, 1)
        report("sfm poses", 0, len(names))
        models = pycolmap.incremental_mapping(db, image_dir, work / "models", mapping, next_image_callback=next_image)
    report("sfm poses", max((r.num_reg_images() for r in models.values()), default=0), len(names))
    shutil.rmtree(work / "models", ignore_errors=True)
    return sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)


# the final refinement of an estimated camera is kept when its principal point stays this share of the image's
# size from the centre and the adjustment's squared error falls by this share at least: a principal point the
# images determine (a phone's fox: 6 %; an exact pinhole's synthetic room, whose point it only moves off: 0.2 %)
PRINCIPAL_POINT_SHARE = 0.1
MIN_COST_DROP = 0.01


def refine_camera(rec):
    """``rec`` (one estimated SIMPLE_RADIAL camera) after a final bundle adjustment with the principal point free
    and the camera as OPENCV (two focal lengths, two radial and two tangential terms): COLMAP's incremental
    mapper holds the principal point at the image centre, a phone's lies pixels away, and the cameras then turn
    by a fraction of a degree against their true orientations. A new reconstruction, or None (``rec`` is
    kept) when the principal point leaves the centre by more than PRINCIPAL_POINT_SHARE of the image or the
    squared reprojection error falls by less than MIN_COST_DROP (a point the images do not determine)."""
    import pycolmap

    if len(rec.cameras) != 1 or next(iter(rec.cameras.values())).model.name != "SIMPLE_RADIAL":
        return None
    out = pycolmap.Reconstruction(rec)
    cid, cam = next(iter(out.cameras.items()))
    f, cx, cy, k = cam.params
    out.cameras[cid] = pycolmap.Camera(
        model="OPENCV", width=cam.width, height=cam.height, params=[f, f, cx, cy, k, 0, 0, 0], camera_id=cid
    )
    from ..pose_refinement import quiet_colmap

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = True
    options.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in out.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    with quiet_colmap("FATAL"):  # the adjuster itself: pycolmap.bundle_adjustment logs past the level
        cost = pycolmap.create_default_bundle_adjuster(options, config, out).solve().ceres_summary
    out.update_point_3d_errors()
    c = out.cameras[cid]
    off = np.abs(np.array(c.params[2:4]) - [c.width / 2, c.height / 2]) / [c.width, c.height]
    keep = np.all(off <= PRINCIPAL_POINT_SHARE) and cost.final_cost <= (1 - MIN_COST_DROP) * cost.initial_cost
    return out if keep else None


def _camera(c) -> Camera:
    model = c.model.name
    if model not in SUPPORTED_MODELS:
        raise InputError(f"pose estimation gave an unsupported camera model {model}")
    return Camera(model, int(c.width), int(c.height), np.array(c.params, np.float64))


def sequence_from_reconstruction(rec, image_dir: Path) -> Sequence:
    """The registered images of ``rec`` as a posed Sequence rooted at ``image_dir`` (names: COLMAP's)."""
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    cameras = {int(im.camera_id): _camera(rec.cameras[im.camera_id]) for im in images}
    frames = [
        Frame(im.name, image_dir / im.name, int(im.camera_id), from_rigid3d(im.cam_from_world())) for im in images
    ]
    return Sequence(image_dir, FORMAT, cameras, frames)


def _scale(rec, s: float) -> None:
    import pycolmap

    rec.transform(pycolmap.Sim3d(float(s), pycolmap.Rotation3d(), np.zeros(3)))


def _write(models: list, work: Path, opts: SfmOptions) -> None:
    for i, rec in enumerate(models):
        if opts.scale is not None:
            _scale(rec, opts.scale)
        d = work / "sparse" / str(i)
        d.mkdir(parents=True)
        rec.write(str(d))


def _commit(work: Path, out: Path) -> None:
    """Put the complete reconstruction ``work`` at ``out``, replacing an earlier one."""
    if out.exists():
        old = out.with_name(out.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        out.rename(old)
        work.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        work.rename(out)


def estimate_poses(
    image_dir,
    out,
    options: SfmOptions | None = None,
    progress: Callable | None = None,
    prepare: Callable[[Path], tuple[Path, list[str]]] | None = None,
) -> SfmResult:
    """Pose the images of ``image_dir`` (module doc) and keep the reconstruction in ``out``.
    ``progress(stage, done, total)`` sees the stages. ``prepare(work)``, when given, writes the images
    itself into the work folder (the frames of a video) and returns (their folder, their names); the
    folder is then ``out``'s, after the rename. Raises PosesNotFound when no image is posed."""
    opts = options or SfmOptions()
    out = check_output(out).absolute()
    report = progress or (lambda *a: None)
    t0 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    work.chmod(0o755)  # mkdtemp's is private; the reconstruction is a folder like any other
    try:
        if prepare is not None:
            image_dir, names = prepare(work)
        else:
            image_dir = Path(image_dir).absolute()
            names = opts.image_names if opts.image_names is not None else list_images(image_dir)
        if not names:
            raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {image_dir}")
        _check_camera(opts.camera, image_dir / names[0])
        anchors, missing = check_anchors(opts.anchors, names) if opts.anchors is not None else (None, [])
        matcher = opts.resolved_matcher(len(names))
        try:
            models = _reconstruct(image_dir, names, work, opts, matcher, report)
        except (RuntimeError, ValueError) as e:  # pycolmap's failures (an unreadable database, ...)
            raise FavormapError(f"pose estimation of the images of {image_dir} failed: {first_line(e)}") from None
        if not models or models[0].num_reg_images() == 0:
            raise PosesNotFound(
                f"no pose could be estimated for any of the {len(names)} images of {image_dir} (too little overlap "
                "between them, too little texture, or a camera that moves too little)"
            )
        refined = None if opts.camera is not None or opts.camera_per_image else refine_camera(models[0])
        models[0] = refined or models[0]
        fit = anchor_reconstruction(models[0], anchors, missing) if anchors is not None else None
        _write(models, work, opts)
        final_dir = out / image_dir.relative_to(work) if image_dir.is_relative_to(work) else image_dir
        result = _result(models, names, out, final_dir, matcher, opts, time.perf_counter() - t0)
        result.camera_refined = refined is not None
        if fit is not None:
            result.anchors, result.scale = fit.to_dict(), fit.scale
        (work / MARKER).write_text(json.dumps(result.to_dict(), indent=1) + "\n")
        _commit(work, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return result


def read_result(out) -> SfmResult:
    """The SfmResult of the reconstruction an earlier :func:`estimate_poses` wrote to ``out``."""
    import pycolmap

    out = Path(out).absolute()
    try:
        note = json.loads((out / MARKER).read_text())
        rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    except (OSError, ValueError, RuntimeError) as e:
        raise InputError(f"{out} holds no reconstruction of favormap ({e})") from None
    image_dir = Path(note["image_dir"])
    seq = sequence_from_reconstruction(rec, image_dir)
    seq.extra["sfm"] = {"reconstruction": str(out / "sparse" / "0")}
    return SfmResult(
        sequence=seq,
        reconstruction_path=out / "sparse" / "0",
        image_dir=image_dir,
        registered=[f.name for f in seq.frames],
        unregistered=list(note["unregistered"]),
        mean_reprojection_error_px=float(note["mean_reprojection_error_px"]),
        mapper=note["mapper"],
        matcher=note["matcher"],
        num_models=int(note["models"]),
        num_points=int(note["points"]),
        scale=note["scale"],
        seconds=float(note["seconds"]),
        other_models=list(note["other_models_registered"]),
        camera_refined=bool(note.get("camera_refined", False)),
        anchors=note.get("anchors"),
    )


def _result(models, names, out, image_dir, matcher, opts, seconds) -> SfmResult:
    rec = models[0]
    seq = sequence_from_reconstruction(rec, image_dir)
    seq.extra["sfm"] = {"reconstruction": str(out / "sparse" / "0")}
    posed = {f.name for f in seq.frames}
    return SfmResult(
        sequence=seq,
        reconstruction_path=out / "sparse" / "0",
        image_dir=image_dir,
        registered=[f.name for f in seq.frames],
        unregistered=[n for n in names if n not in posed],
        mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        mapper="incremental",
        matcher=matcher,
        num_models=len(models),
        num_points=int(rec.num_points3D()),
        scale=opts.scale,
        seconds=seconds,
        other_models=[int(r.num_reg_images()) for r in models[1:]],
    )
