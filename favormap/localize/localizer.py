"""Iterative render -> match -> PnP-RANSAC localization (paper secs. 3.3-3.4).

From the current pose estimate (initially the prior): select the landmarks visible from it through
the spatial index, get their descriptors from a :mod:`descriptor source <.descriptors>` (rendered
from the voxel grids along the rays from the camera centre, by default), match them to the query's
features (mutual nearest neighbours above a cosine threshold) and solve PnP with pycolmap's
LO-RANSAC + refinement. Repeat from the new estimate until it stops moving or ``iterations`` is
reached.

Without a prior (or when the prior's iterations fail) a coarse pose comes from matching the query
against the mean descriptors of all landmarks; the rendering iterations then refine it.

A pose is reported as a success only when it passes every check of :class:`SuccessChecks`:
enough inliers, a large enough inlier ratio, agreement of the last two iterations, inlier
landmarks that are actually visible (in front, inside the image, within their training view range)
from the final pose, and, for a pose refined from a prior with few inliers, agreement with the
estimate found without the prior. Otherwise ``success`` is false and ``message`` names the check that failed.

The stages by module: this one (prior, rendering iterations, the prior-free estimate), :mod:`.blocks`
(rendering and matching on the localizer's threads), :mod:`.pnp` (PnP-RANSAC, local refinement),
:mod:`.refinement` (guided step, weighted refinement), :mod:`.checks` (success checks, result);
settings in :mod:`.config`, results in :mod:`.result`.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext

import numpy as np

from .. import features as feats_mod
from ..errors import InputError
from ..geometry import camera_centers, from_rigid3d, inverse
from ..heap import reuse_freed_blocks
from ..io import Camera
from ..io.images import prepare_query
from ..mapfile import Map
from ..mapfile.model import map_aligns_by_default, map_epipolar_px
from ..threads import rebalance, serial_blas, thread_count
from ..visibility import SpatialIndex, visible_rows
from .blocks import BlockMatching
from .checks import SuccessChecking
from .config import LocalizeConfig
from .descriptors import DescriptorSource, SeenRays, describe, make_source, unit_rows
from .pnp import PoseSolving
from .prefetch import END, QueryFeatures
from .refinement import FinalRefinement
from .result import IterationResult, LocalizationResult, Query


class Localizer(SuccessChecking, FinalRefinement, BlockMatching, PoseSolving):
    """Localizes query images against one map; keep it alive to localize many queries.

    ``descriptor_source`` overrides ``config.descriptors`` (e.g. nearest-view descriptors, which
    need data the map does not hold).

    From a prior, the features are extracted on a worker thread while the first iteration's landmarks are
    looked up and rendered (one thread per query, ended with it); in a sequence, the next image's while this
    one is localized.

    Thread safety: one Localizer may be shared by several threads; :meth:`localize` calls run
    concurrently and give the same results as one after the other (the map's voxel cache takes a
    lock; everything else a call touches is its own or read-only). Threads of one process share
    the torch/OpenCV pools sized by ``config.threads``; on 2 cores, 4 threads sharing one Localizer
    localized as many queries per second as 4 processes, in less memory (tools/bench_load.py)."""

    def __init__(
        self, map_: Map | str, config: LocalizeConfig | None = None, descriptor_source: DescriptorSource | None = None
    ):
        self.config = config or LocalizeConfig()
        self.map = map_ if isinstance(map_, Map) else Map.open(map_)
        self.extractor = feats_mod.create(
            self.map.extractor,
            max_keypoints=self.config.max_keypoints,
            device=None if self.config.device == "cpu" else self.config.device,
        )
        self.index = SpatialIndex(self.map.positions)
        # landmark positions of the geometry (visibility, projections, PnP): the map's, or a stream's
        # refined copy (favormap.localize.stream.LandmarkRefinement); the voxel grids stay where they were trained
        self.positions = self.map.positions
        self.default_camera = (
            self.map.cameras[int(self.map.frame_camera_ids[0])]
            if self.map.num_frames
            else next(iter(self.map.cameras.values()))
        )
        self.scale = float(np.median(self.map.depth_range[:, 0])) if len(self.map) else 1.0
        self.source = descriptor_source or make_source(self.config.descriptors, self.map, self.config.device)
        if self.config.threads is not None:  # asked: the pools and the heap policy are the localizer's to set
            thread_count(self.config.threads)  # after the extractor: sizes torch's pools too if it loaded torch
            # a query's temporaries (rendering stencils, similarity blocks, ~1-10 MB each) from reused heap blocks,
            # not fresh mappings faulted in page by page (favormap.heap): ~8,000 page faults a TUM query
            reuse_freed_blocks()
        if self.config.global_ratio is None:
            self.config = dataclasses.replace(self.config, global_ratio=self.extractor.policy.match_ratio)
        if self.config.match_threshold is None:
            self.config = dataclasses.replace(self.config, match_threshold=self.extractor.policy.match_threshold)
        if self.config.ransac_max_error_px is None:
            thr = self.config.ransac_threshold(map_epipolar_px(self.map.provenance))
            self.config = dataclasses.replace(self.config, ransac_max_error_px=thr)
        self._map_sigma = None  # the map's mapping keypoint noise (px), computed on first use
        self._map_focal = None  # the map's working focal length (px), computed on first use
        self._global = None  # (rows, unit mean descriptors) for prior-free matching, loaded on first use
        self._aligner = None  # favormap.localize.align.PlaneAligner (LocalizeConfig.align)
        self._helpers: ThreadPoolExecutor | None = None  # helper threads (_pool), started on first use
        self._pool_lock = threading.Lock()
        if self.config.align is None:
            self.config = dataclasses.replace(self.config, align=map_aligns_by_default(self.map.provenance))
        if self.config.align:
            from .align import AlignConfig, PlaneAligner

            self._aligner = PlaneAligner(
                self.map, self.config.align_images, AlignConfig(references=self.config.align_references)
            )

    def close(self):
        if self._helpers is not None:
            self._helpers.shutdown()
            self._helpers = None
        self.map.close()

    # -- inputs --------------------------------------------------------------------------------------
    def prepare(self, image, camera: Camera | None = None):
        """Query image (path or RGB array at the camera's resolution) -> (working image, pinhole camera)."""
        return prepare_query(image, camera or self.default_camera, self.map.max_side)

    @staticmethod
    def _check_prior(prior) -> np.ndarray:
        prior = np.asarray(prior, np.float64)
        if prior.shape != (4, 4) or not np.all(np.isfinite(prior)):
            raise InputError("the prior pose must be a finite 4x4 matrix")
        R = prior[:3, :3]
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise InputError("the prior pose is not a rigid transform (rotation not orthonormal)")
        return prior

    # -- main loop -----------------------------------------------------------------------------------
    def localize_sequence(
        self,
        images,
        first_prior: np.ndarray | None = None,
        camera: Camera | None = None,
        motion: str = "constant-velocity",
        refine_landmarks: bool = True,
    ):
        """Localize a stream of query images in order (a robot's camera), yielding one result per
        image: each image's prior comes from the poses already estimated
        (:class:`favormap.localize.motion.MotionPrior`), so only the first needs one, or none. With
        ``refine_landmarks`` the landmarks each localized frame saw are triangulated again with its
        observations, for the frames after it (:class:`favormap.localize.stream.LandmarkRefinement`;
        the map itself is not changed).

        Each image is taken from ``images``, read and its features extracted on a worker thread while the image
        before it is localized (one image ahead; :mod:`.prefetch`): an image that cannot be read fails when its
        turn comes, after the results of those before it."""
        from .stream import Stream

        images = iter(images)

        def next_image():  # on the extraction thread: the stream's next image, or END past its end
            return next(images, END)

        pool = ThreadPoolExecutor(1, thread_name_prefix="favormap-extract")
        try:
            with Stream(self, first_prior, motion, refine_landmarks) as stream:
                upcoming = self._prefetch(pool, next_image, camera)
                refine = None
                while True:
                    frame = upcoming
                    if frame.prepared() is None:
                        return
                    # the next image is read and extracted once this one's features are out: while this one is
                    # localized
                    upcoming = self._prefetch(pool, next_image, camera)
                    # the landmarks the last frame refines are triangulated before this frame's poses use them,
                    # beside its extraction where that is still running
                    res = self._localize_rig(None, stream.prior(), camera, refine, frame)
                    refine = stream.update_later(res)
                    yield res
        finally:  # a stream left early reads no further image
            pool.shutdown(wait=True, cancel_futures=True)

    def _prefetch(self, pool: ThreadPoolExecutor, image, camera) -> QueryFeatures:
        frame = QueryFeatures()
        pool.submit(frame.run, self, image, camera)
        return frame

    def localize(
        self, image, prior_cam_from_world: np.ndarray | None = None, camera: Camera | None = None
    ) -> LocalizationResult:
        """Localize one query image. Without a prior, a coarse pose is found first by matching
        against all landmarks (see ``LocalizeConfig.global_fallback``)."""
        return self._localize_rig(image, prior_cam_from_world, camera)

    def _localize_rig(self, image, prior_cam_from_world, camera, meanwhile=None, frame=None) -> LocalizationResult:
        """:meth:`localize`; ``meanwhile()`` runs before the landmark positions are first used, while the
        features are extracted where they are extracted on a worker thread. ``frame``: the image's
        :class:`~.prefetch.QueryFeatures`, where already under way (``image`` is then not used)."""
        rebalance()  # pools sized by the rule follow the machine's load (favormap.threads; else a no-op)
        prior = None if prior_cam_from_world is None else self._check_prior(prior_cam_from_world)
        rig = self.map.stored_cam_from_rig is not None
        # with the pools in its hands (config.threads), BLAS runs on the thread that calls it: the localizer's
        # stages run on threads of their own (favormap.threads.serial_blas)
        with serial_blas() if self.config.threads is not None else nullcontext():
            res = self._localize(
                image, self.camera_pose(prior) if rig and prior is not None else prior, camera, meanwhile, frame
            )
        res.image_cam_from_world = res.cam_from_world
        if rig:  # the map's cameras are turned against the poses it was built from: report in their frame
            res.cam_from_world = self.rig_pose(res.cam_from_world)
            res.estimate = None if res.estimate is None else self.rig_pose(res.estimate)
            for it in res.iterations:
                it.cam_from_world = self.rig_pose(it.cam_from_world)
            if res.covariance is not None:
                res.covariance = res.covariance.turned(inverse(self.map.cam_from_rig)[:3, :3])
        res.prior = prior
        return res

    def camera_pose(self, rig_from_world: np.ndarray) -> np.ndarray:
        """The pose of the map's camera for a pose in the convention of the poses the map was built from
        (``Map.cam_from_rig @ rig_from_world``; the same pose for maps without frames/cam_from_rig)."""
        return self.map.cam_from_rig @ np.asarray(rig_from_world, np.float64)

    def rig_pose(self, cam_from_world: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`camera_pose`."""
        return inverse(self.map.cam_from_rig) @ np.asarray(cam_from_world, np.float64)

    def _localize(
        self, image, prior: np.ndarray | None, camera: Camera | None, meanwhile=None, frame: QueryFeatures | None = None
    ) -> LocalizationResult:
        cfg = self.config
        t = {k: 0.0 for k in ("extraction", "visibility", "loading", "rendering", "matching", "pnp")}
        seen = None
        if cfg.rerender_angle_deg > 0 and getattr(self.source, "one_per_landmark", False):
            seen = SeenRays(self.map.positions, cfg.rerender_angle_deg)
        first_rows = None
        pool = None
        if frame is None:
            frame = QueryFeatures()
            if prior is not None and seen is not None:  # extracted beside the first rendering, below
                pool = ThreadPoolExecutor(1, thread_name_prefix="favormap-extract")
                pool.submit(frame.run, self, image, camera)
            else:
                frame.run(self, image, camera)
        try:
            img, cam = frame.prepared()
            if prior is not None and seen is not None:
                # the first iteration's landmarks and descriptors need only the prior: they are looked up and
                # rendered while the features are extracted (the extractor leaves part of the cores idle)
                first_rows = self._visible(cam, prior, t)
                describe(self.source, first_rows, prior, t, seen)
            if meanwhile is not None:
                meanwhile()
            feats = frame.features()
        finally:
            if pool is not None:
                pool.shutdown()
        t["extraction"] = frame.seconds
        qdesc = np.asarray(feats.descriptors, np.float32)
        q = Query(feats, qdesc, cam, seen=seen)
        if cfg.align:
            q.image = img

        if prior is not None:
            res = self._refine(q, prior, [], t, first_rows=first_rows)
            self._confirm(q, res, prior, t)
            if res.success or not cfg.global_fallback:
                return res
            first = res
        else:
            if not cfg.global_fallback:
                raise InputError("localization without a prior needs global_fallback=True")
            first = None
        coarse, it = self._global_pose(q, t)
        if coarse is None:
            return first or self._result(
                q,
                None,
                [it],
                t,
                np.eye(4),
                "without a prior, matching against all landmarks "
                f"found no pose ({it.num_matches} matches, {it.num_inliers} inliers)",
            )
        res = self._refine(q, coarse, (first.iterations if first is not None else []) + [it], t, anchor=coarse)
        self._confirm(q, res, coarse, t)  # the refinement must stay where the coarse pose put it
        if not res.success and first is not None:
            res.message = f"{first.message}; from a coarse pose found without the prior: {res.message}"
            res.cam_from_world = prior
        return res

    def _global_pose(self, q: Query, t: dict):
        """Coarse pose without a prior: mutual matches against every landmark's mean descriptor
        (computed once per query)."""
        if q.global_pose is None:
            q.global_pose = self._global_pose_uncached(q, t)
        return q.global_pose

    def _global_pose_uncached(self, q: Query, t: dict):
        cfg = self.config
        s = time.perf_counter()
        if self._global is None:
            rows = np.arange(len(self.map))
            if len(rows) > cfg.global_max_landmarks:
                rows = np.sort(np.argsort(-self.map.track_length, kind="stable")[: cfg.global_max_landmarks])
            self._global = (rows, unit_rows(self.map.mean_descriptors(rows)))
        rows, d = self._global
        t["loading"] += time.perf_counter() - s
        m = self._match_all(q, d, True, cfg.global_ratio, t)
        q.global_matches = (self.positions[rows[m[:, 0]]], m[:, 1])
        ans = self._pnp(q, *q.global_matches, t)
        n_in = int(ans["num_inliers"]) if ans is not None else 0
        ok = ans is not None and n_in >= cfg.coarse_min_inliers
        # a RANSAC pose below coarse_min_inliers is kept in the iteration: it may still confirm a refined pose
        # (SuccessChecks.confirm_min_inliers), but it is no coarse pose to refine from
        pose = from_rigid3d(ans["cam_from_world"]) if ans is not None else np.eye(4)
        return (pose if ok else None), IterationResult(pose, len(rows), len(m), n_in, ok, kind="global")

    def _visible(self, cam: Camera, pose: np.ndarray, t: dict) -> np.ndarray:
        """Rows of the landmarks visible from ``pose`` with the query's camera ``cam`` (timed into
        ``t["visibility"]``)."""
        s = time.perf_counter()
        rows = visible_rows(
            self.index,
            cam,
            pose,
            self.map.view_dir,
            self.map.view_angle,
            self.map.depth_range,
            self.config.view_limits,
        )
        t["visibility"] += time.perf_counter() - s
        return rows

    def _refine(
        self,
        q: Query,
        start: np.ndarray,
        iters: list[IterationResult],
        t: dict,
        anchor: np.ndarray | None = None,
        first_rows: np.ndarray | None = None,
    ) -> LocalizationResult:
        """The rendering iterations from ``start``, then the guided step and the weighted refinement.

        ``anchor``: the prior-free estimate this refinement starts from. A pose with fewer than
        ``checks.confirm_below_inliers`` inliers that leaves it by more than
        ``checks.max_iteration_change`` would be refused by :meth:`_confirm`; for such a RANSAC
        solution the iteration takes the pose it rendered from, refined on its own inliers among the
        same matches (:meth:`_local_pnp`), instead. On the fox's wallpaper (query 0072 of the
        extrapolation split) RANSAC preferred a false consensus 6.8 units away (46 inliers at 4 px,
        on one repeated flower) to the correct pose (38 inliers at 4 px, 0.015 units from the truth):
        a larger inlier set is no evidence against a pose that the prior-free estimate confirms.

        ``first_rows``: the landmarks visible from ``start``, where already looked up."""
        cfg = self.config
        pose = start
        last = None
        rows = self._visible(q.cam, pose, t) if first_rows is None else first_rows
        for k in range(cfg.iterations):
            drows, m, sims = self._describe_and_match(q, rows, pose, t)
            points = self.positions[drows[m[:, 0]]]
            ans = self._pnp(q, points, m[:, 1], t)
            if anchor is not None and ans is not None and self._leaves(ans, anchor):
                ans = self._local_pnp(q, pose, points, m[:, 1], t)
            ans = self._fit_tightly(q, ans, points, m[:, 1], t)
            n_in = int(ans["num_inliers"]) if ans is not None else 0
            ok = ans is not None and n_in >= cfg.checks.min_inliers
            new_pose = from_rigid3d(ans["cam_from_world"]) if ok else pose
            iters.append(IterationResult(new_pose, len(rows), len(m), n_in, ok))
            if not ok:
                break
            last = dict(
                matches=np.c_[drows[m[:, 0]], m[:, 1]], inliers=np.asarray(ans["inlier_mask"], bool), similarity=sims
            )
            if k == cfg.iterations - 1:
                pose = new_pose
                break
            new_rows = self._visible(q.cam, new_pose, t)
            changed = self._changed_share(rows, pose, new_rows, new_pose)
            pose, rows = new_pose, new_rows
            if changed < cfg.stop_change:
                break
        cov = None
        weighted = last is not None and iters[-1].success and cfg.landmark_sigma_px != 0
        if (
            last is not None
            and cfg.guided_radius_px > 0
            and (cfg.guided_below_inliers is None or int(last["inliers"].sum()) < cfg.guided_below_inliers)
        ):
            last, cov = self._guided_steps(q, pose, iters, last, weighted, t)
        elif weighted:
            cov = self._weighted(q, iters[-1], last, t)
        res = self._result(q, last, iters, t, start)
        res.covariance = cov if res.success else None
        return res

    def _changed_share(self, rows: np.ndarray, pose: np.ndarray, new_rows: np.ndarray, new_pose: np.ndarray) -> float:
        """The share of the landmarks visible from ``new_pose`` (``new_rows``) that an iteration from there
        would see differently from one at ``pose`` (visible ``rows``, both sorted): those visible from only
        one of them, and those whose ray from the camera centre turns by more than
        ``LocalizeConfig.rerender_angle_deg`` (all of them when that angle is 0: rendered every time)."""
        angle = self.config.rerender_angle_deg
        if len(new_rows) == 0 or angle <= 0:
            return 1.0
        both = np.intersect1d(rows, new_rows, assume_unique=True)
        changed = len(rows) + len(new_rows) - 2 * len(both)
        X = np.asarray(self.map.positions[both], np.float64)
        a, b = X - camera_centers(pose), X - camera_centers(new_pose)
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        changed += int(np.count_nonzero(cos < np.cos(np.radians(angle))))
        return changed / len(new_rows)


def localize(
    map_, image, prior_cam_from_world=None, camera: Camera | None = None, config: LocalizeConfig | None = None
) -> LocalizationResult:
    """One-shot convenience wrapper around :class:`Localizer`."""
    loc = Localizer(map_, config)
    try:
        return loc.localize(image, prior_cam_from_world, camera)
    finally:
        if not isinstance(map_, Map):
            loc.close()
