"""The pycolmap-SIFT structure baseline every favormap accuracy number is compared with.

A plain structure-based localizer built with pycolmap from the same undistorted, resized images
and pinhole cameras favormap uses (``favormap.io.load_image``):

* build: COLMAP SIFT on every working image into a COLMAP database, exhaustive (small sequences)
  or sequential matching with geometric verification, then ``pycolmap.triangulate_points`` from
  the known cameras and poses (poses stay fixed). Every 3D point gets one descriptor: the mean of
  its track's L2-normalised (RootSIFT, as COLMAP stores them) descriptors, normalised again.
* localize: COLMAP SIFT on the working query image, nearest neighbour over all 3D points with
  Lowe's ratio test, then ``pycolmap.estimate_and_refine_absolute_pose`` (COLMAP's LO-RANSAC with
  its default options and non-linear refinement). No prior pose is used.
"""

from __future__ import annotations

import contextlib
import copy
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import FavormapError, InputError
from ..geometry import from_rigid3d, to_rigid3d
from ..io import Camera, Sequence, load_image
from ..io.images import prepare_query
from ..pose_refinement import quiet_colmap

MATCHING_MODES = ("auto", "exhaustive", "sequential")


@dataclass
class StructureBaselineConfig:
    max_side: int | None = 640  # working image size, as favormap's build/localize
    max_num_features: int = 8192  # COLMAP's default
    ratio: float = 0.8  # Lowe's ratio test (query feature -> 3D points)
    min_inliers: int = 12  # success threshold on the PnP inliers
    matching: str = "auto"  # auto: exhaustive up to exhaustive_max_frames frames, else sequential
    exhaustive_max_frames: int = 60
    sequential_overlap: int = 10
    ransac_max_error_px: float | None = None  # None: pycolmap's default (12 px in pycolmap 4.2)
    num_threads: int = -1  # COLMAP extraction / matching threads (-1: all cores)
    seed: int = 0  # RANSAC seed (reproducible results)


@dataclass
class BaselineResult:
    success: bool
    cam_from_world: np.ndarray  # 4x4 RANSAC estimate (also below min_inliers); identity if none
    num_matches: int
    num_inliers: int
    seconds: float
    keypoints: np.ndarray  # (M, 2) query keypoints in the working image (COLMAP pixel convention)
    matches: np.ndarray  # (K, 2) [point index, keypoint index]
    inlier_mask: np.ndarray  # (K,) bool
    message: str = ""
    camera: Camera | None = None  # the working pinhole camera of the query


def _normalize(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc, np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _extractor(cfg: StructureBaselineConfig):
    import pycolmap

    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.max_num_features = cfg.max_num_features
    opts.num_threads = cfg.num_threads
    return pycolmap.FeatureExtractor.create(opts, device=pycolmap.Device.cpu)


def _extract(extractor, rgb: np.ndarray):
    """COLMAP SIFT on an RGB uint8 image -> ((M, 6) float32 affine keypoints, FeatureDescriptors)."""
    import pycolmap

    kps, desc = extractor.extract(pycolmap.Bitmap.from_array(np.ascontiguousarray(rgb)).clone_as_grey())
    kp = np.array([[k.x, k.y, k.a11, k.a12, k.a21, k.a22] for k in kps], np.float32).reshape(-1, 6)
    return kp, desc


def ratio_match(points_desc: torch.Tensor, query_desc: torch.Tensor, ratio: float, chunk: int = 2048) -> np.ndarray:
    """(K, 2) [point index, query index]: each query descriptor's nearest point descriptor (unit
    vectors, Euclidean distance), kept when it is closer than ``ratio`` times the second nearest."""
    if len(points_desc) < 2 or len(query_desc) == 0:
        return np.zeros((0, 2), np.int64)
    out = []
    for s in range(0, len(query_desc), chunk):
        sim, idx = torch.topk(query_desc[s : s + chunk] @ points_desc.T, 2, dim=1)
        dist = torch.sqrt(torch.clamp(2 - 2 * sim, min=0))
        keep = torch.nonzero(dist[:, 0] < ratio * dist[:, 1]).squeeze(1)
        out.append(torch.stack([idx[keep, 0], keep + s], 1))
    return torch.cat(out).cpu().numpy().astype(np.int64)


@dataclass
class PointTracks:
    """The mapping observations of the baseline's points (what :class:`PointRefinement` needs)."""

    point: np.ndarray  # (O,) point row of each observation
    frame: np.ndarray  # (O,) mapping frame
    xy: np.ndarray  # (O, 2) keypoint (px, COLMAP convention)
    cam_from_world: np.ndarray  # (F, 4, 4) the mapping frames' poses
    K: np.ndarray  # (F, 3, 3) their working pinhole intrinsics


class StructureBaseline:
    """SIFT 3D points with mean descriptors, triangulated by pycolmap from known poses."""

    def __init__(
        self,
        points3d: np.ndarray,
        descriptors: np.ndarray,
        track_lengths: np.ndarray,
        config: StructureBaselineConfig,
        reconstruction=None,
        tracks: PointTracks | None = None,
    ):
        import pycolmap

        self.points3d = np.asarray(points3d, np.float64).reshape(-1, 3)
        self.descriptors = _normalize(np.asarray(descriptors).reshape(-1, 128))
        self.track_lengths = np.asarray(track_lengths, np.int64).reshape(-1)
        self.config = config
        self.reconstruction = reconstruction  # pycolmap.Reconstruction (None for subsets)
        self.tracks = tracks  # the points' mapping observations (None for subsets)
        default = pycolmap.AbsolutePoseEstimationOptions().ransac.max_error
        self.ransac_max_error_px = float(default if config.ransac_max_error_px is None else config.ransac_max_error_px)
        self._desc = torch.from_numpy(self.descriptors)
        self._extractor = None

    def __len__(self) -> int:
        return len(self.points3d)

    # -- build ---------------------------------------------------------------------------------
    @classmethod
    def build(cls, seq: Sequence, config: StructureBaselineConfig | None = None, workdir=None) -> StructureBaseline:
        """Extract, match and triangulate ``seq`` (known cameras and poses) in ``workdir``
        (a temporary directory, removed afterwards, by default)."""
        cfg = config or StructureBaselineConfig()
        if cfg.matching not in MATCHING_MODES:
            raise InputError(f"unknown matching mode {cfg.matching!r} ({', '.join(MATCHING_MODES)})")
        if len(seq) < 2:
            raise FavormapError(f"the structure baseline needs at least 2 posed frames, got {len(seq)}")
        with contextlib.ExitStack() as stack:
            if workdir is None:
                workdir = stack.enter_context(tempfile.TemporaryDirectory(prefix="favormap_baseline_"))
            stack.enter_context(quiet_colmap())
            return cls._build(seq, cfg, Path(workdir))

    @classmethod
    def _build(cls, seq: Sequence, cfg: StructureBaselineConfig, wd: Path) -> StructureBaseline:
        import pycolmap

        images_dir, db_path, out_dir = wd / "images", wd / "database.db", wd / "sparse"
        images_dir.mkdir(parents=True, exist_ok=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        db_path.unlink(missing_ok=True)
        extractor = _extractor(cfg)
        rec = pycolmap.Reconstruction()
        cam_ids: dict[int, int] = {}
        descs: dict[int, np.ndarray] = {}
        with pycolmap.Database.open(db_path) as db:
            for i, frame in enumerate(seq.frames):
                rgb, cam = load_image(frame.image_path, seq.cameras[frame.camera_id], cfg.max_side)
                if frame.camera_id not in cam_ids:
                    pc = cam.to_pycolmap()
                    pc.camera_id = len(cam_ids) + 1
                    pc.has_prior_focal_length = True  # known intrinsics: verify with E, not F
                    db.write_camera(pc, use_camera_id=True)
                    rig = pycolmap.Rig(rig_id=pc.camera_id)
                    rig.add_ref_sensor(pc.sensor_id)
                    db.write_rig(rig, use_rig_id=True)
                    rec.add_camera_with_trivial_rig(pc)
                    cam_ids[frame.camera_id] = pc.camera_id
                name, image_id, cid = f"{i:06d}.png", i + 1, cam_ids[frame.camera_id]
                cv2.imwrite(str(images_dir / name), rgb[..., ::-1])
                kp, desc = _extract(extractor, rgb)
                image = pycolmap.Image(name=name, camera_id=cid, image_id=image_id)
                image.frame_id = image_id
                db_frame = pycolmap.Frame(frame_id=image_id, rig_id=cid)
                db_frame.add_data_id(image.data_id)
                db.write_frame(db_frame, use_frame_id=True)  # a frame first: write_image checks it
                db.write_image(image, use_image_id=True)
                db.write_keypoints(image_id, kp)
                db.write_descriptors(image_id, desc)
                descs[image_id] = np.asarray(desc.data)
                rec.add_image_with_trivial_frame(
                    pycolmap.Image(name=name, keypoints=kp[:, :2].astype(np.float64), camera_id=cid, image_id=image_id),
                    to_rigid3d(frame.cam_from_world),
                )
        if sum(len(d) for d in descs.values()) == 0:
            raise FavormapError("the structure baseline found no SIFT features in the images")
        mopts = pycolmap.FeatureMatchingOptions()
        mopts.num_threads = cfg.num_threads
        exhaustive = cfg.matching == "exhaustive" or (cfg.matching == "auto" and len(seq) <= cfg.exhaustive_max_frames)
        if exhaustive:
            pycolmap.match_exhaustive(db_path, matching_options=mopts, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions(overlap=cfg.sequential_overlap)
            pycolmap.match_sequential(
                db_path, matching_options=mopts, pairing_options=pairing, device=pycolmap.Device.cpu
            )
        rec = pycolmap.triangulate_points(rec, db_path, images_dir, out_dir)
        return cls._from_reconstruction(rec, descs, cfg)

    @classmethod
    def _from_reconstruction(cls, rec, descs: dict[int, np.ndarray], cfg: StructureBaselineConfig) -> StructureBaseline:
        if rec.num_points3D() == 0:
            raise FavormapError("pycolmap triangulated no 3D points (too few verified matches between the frames?)")
        offsets, start = {}, 0
        for image_id in sorted(descs):
            offsets[image_id], start = start, start + len(descs[image_id])
        all_desc = torch.from_numpy(_normalize(np.concatenate([descs[k] for k in sorted(descs)])))
        xyz, rows, lengths, obs_frame, obs_xy = [], [], [], [], []
        frame_of = {image_id: f for f, image_id in enumerate(sorted(descs))}
        for p in rec.points3D.values():
            els = p.track.elements
            xyz.append(p.xyz)
            lengths.append(len(els))
            rows.extend(offsets[e.image_id] + e.point2D_idx for e in els)
            obs_frame.extend(frame_of[e.image_id] for e in els)
            obs_xy.extend(rec.images[e.image_id].points2D[e.point2D_idx].xy for e in els)
        lengths_np = np.asarray(lengths, np.int64)
        owner = torch.from_numpy(np.repeat(np.arange(len(lengths_np)), lengths_np))
        mean = torch.zeros(len(lengths_np), 128).index_add_(0, owner, all_desc[torch.as_tensor(rows)])
        poses, Ks = [], []
        for image_id in sorted(descs):
            image = rec.images[image_id]
            cfw = image.cam_from_world
            poses.append(from_rigid3d(cfw() if callable(cfw) else cfw))
            Ks.append(rec.cameras[image.camera_id].calibration_matrix())
        xy = np.asarray(obs_xy, np.float64).reshape(-1, 2)
        tracks = PointTracks(owner.numpy(), np.asarray(obs_frame, np.int64), xy, np.stack(poses), np.stack(Ks))
        return cls(np.asarray(xyz), mean.numpy(), lengths_np, cfg, rec, tracks)

    def subset(self, max_points: int) -> StructureBaseline:
        """The same baseline restricted to its ``max_points`` longest-track points."""
        keep = np.sort(np.argsort(-self.track_lengths, kind="stable")[: max(0, int(max_points))])
        return StructureBaseline(
            self.points3d[keep], self.descriptors[keep], self.track_lengths[keep], replace(self.config)
        )

    # -- localize ------------------------------------------------------------------------------
    def prepare(self, image, camera: Camera) -> tuple[np.ndarray, Camera]:
        """Query image (path or RGB array at the camera's resolution) -> (working image, pinhole
        camera), exactly as ``Localizer.prepare``."""
        return prepare_query(image, camera, self.config.max_side)

    def localize(self, image, camera: Camera) -> BaselineResult:
        """Localize one query image (no prior): SIFT, ratio-test matching to all 3D points, PnP."""
        import pycolmap

        cfg = self.config
        t0 = time.perf_counter()
        img, cam = self.prepare(image, camera)
        with quiet_colmap():
            if self._extractor is None:
                self._extractor = _extractor(cfg)
            kp, desc = _extract(self._extractor, img)
            qdesc = torch.from_numpy(_normalize(np.asarray(desc.data).reshape(-1, 128)))
            m = ratio_match(self._desc, qdesc, cfg.ratio)
            pose, n_in, mask, msg = np.eye(4), 0, np.zeros(len(m), bool), ""
            if len(m) >= 4:
                est = pycolmap.AbsolutePoseEstimationOptions()
                est.ransac.max_error = self.ransac_max_error_px
                est.ransac.random_seed = cfg.seed
                ans = pycolmap.estimate_and_refine_absolute_pose(
                    kp[m[:, 1], :2].astype(np.float64), self.points3d[m[:, 0]], cam.to_pycolmap(), est
                )
                if ans is not None:
                    pose, n_in = from_rigid3d(ans["cam_from_world"]), int(ans["num_inliers"])
                    mask = np.asarray(ans["inlier_mask"], bool)
        success = n_in >= cfg.min_inliers
        if not success:
            msg = f"too few inliers ({len(m)} matches, {n_in} inliers; need {cfg.min_inliers})"
        return BaselineResult(
            success, pose, len(m), n_in, time.perf_counter() - t0, kp[:, :2].copy(), m, mask, msg, cam
        )


class PointRefinement:
    """The baseline localizing a stream of queries with its points refined from it, as
    :class:`favormap.localize.stream.LandmarkRefinement` refines a favormap map's landmarks (the
    like-for-like of favormap's ``stream`` prior mode): after each localized query, its inlier
    observations are added to those points' mapping observations and the points are triangulated
    again (favormap's robust triangulation), for the queries after it.

    The same rules as favormap's: only points whose position covariance, projected into the query,
    has a standard deviation of at least ``min_uncertainty_px`` take its observations (the
    covariance model of :func:`favormap.localize.refine.position_covariances`, from the point's
    track, its views' spread and its own reprojection error); a refined point may move at most
    ``max_move`` times favormap's voxel box (``box_factor`` * its nearest observation's depth /
    focal length) from where pycolmap put it. The baseline passed in is not modified: the
    refinement localizes with a copy of its points."""

    def __init__(
        self,
        baseline: StructureBaseline,
        max_observations: int = 10,
        max_move: float = 0.5,
        box_factor: float = 7.0,
        min_uncertainty_px: float = 0.25,
    ):
        from ..geometry import camera_centers, project, view_geometry
        from .refine import position_covariances, reprojection_pixel_sigma
        from .stream import Retriangulation

        t = baseline.tracks
        if t is None:
            raise FavormapError("this baseline has no mapping observations to refine its points with (a subset?)")
        self.baseline = copy.copy(baseline)
        self.baseline.points3d = np.array(baseline.points3d, np.float64, copy=True)
        self.min_uncertainty_px = float(min_uncertainty_px)
        n, X = len(baseline), self.baseline.points3d
        uv, depth = project(t.K[t.frame], t.cam_from_world[t.frame], X[t.point], with_depth=True)
        f = t.K[t.frame, 0, 0]
        scale = np.full(n, np.inf)
        np.minimum.at(scale, t.point, np.abs(depth) / f)
        # the covariance model favormap's landmarks get, from the points' tracks
        length = np.bincount(t.point, minlength=n)
        err = np.bincount(t.point, np.linalg.norm(uv - t.xy, axis=1), n) / np.maximum(length, 1)
        view_dir, view_angle, depth_range = view_geometry(X, t.point, camera_centers(t.cam_from_world)[t.frame])
        sigma = reprojection_pixel_sigma(err, length)
        self._cov = position_covariances(
            depth_range.mean(axis=1), length, view_angle, view_dir, sigma, float(np.median(f))
        )
        self.core = Retriangulation(
            X, t.point, t.frame, t.xy, t.cam_from_world, t.K, max_move * box_factor * scale, max_observations
        )

    @property
    def points3d(self) -> np.ndarray:
        return self.baseline.points3d

    def localize(self, image, camera: Camera) -> BaselineResult:
        """Localize the next query of the stream against the points refined so far, then refine."""
        from .refine import projected_std

        res = self.baseline.localize(image, camera)
        if res.success:
            inl = np.asarray(res.matches, np.int64).reshape(-1, 2)[np.asarray(res.inlier_mask, bool)]
            if len(inl) and self.min_uncertainty_px > 0:
                std = projected_std(self.points3d[inl[:, 0]], self._cov[inl[:, 0]], res.cam_from_world, res.camera.K)
                inl = inl[std >= self.min_uncertainty_px]
            self.core.add(res.cam_from_world, res.camera.K, inl[:, 0], res.keypoints[inl[:, 1]])
        return res
