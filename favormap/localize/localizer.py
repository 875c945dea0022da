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
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from .. import features as feats_mod
from ..errors import InputError
from ..geometry import from_rigid3d, pose_error, project, to_rigid3d
from ..io import Camera
from ..io.images import prepare_query
from ..mapfile import Map
from ..mapfile.model import map_aligns_by_default
from ..threads import rebalance, thread_count
from ..visibility import SpatialIndex, visible_mask, visible_rows
from .config import LocalizeConfig
from .descriptors import DescriptorSource, describe, make_source, unit_rows
from .matching import distinct_pairs, match_descriptors, match_near, pair_in, pair_similarity
from .refine import (
    PoseCovariance,
    estimate_noise,
    landmark_covariances,
    mahalanobis2,
    mapping_pixel_sigma,
    projection_information,
    refine_pose,
)


@dataclass
class IterationResult:
    cam_from_world: np.ndarray
    num_visible: int
    num_matches: int
    num_inliers: int
    success: bool  # PnP found a pose with enough inliers (not yet the final checks)
    kind: str = "render"  # "render" (from the previous estimate) or "global" (no prior)


@dataclass
class LocalizationResult:
    success: bool
    cam_from_world: np.ndarray  # final estimate (the prior when not successful)
    num_matches: int
    num_inliers: int
    iterations: list[IterationResult]
    timings: dict[str, float]
    message: str = ""
    checks: dict = field(default_factory=dict)  # measured values of the success checks
    # for visualisation / analysis (last successful iteration)
    keypoints: np.ndarray | None = None
    matches: np.ndarray | None = None  # (K, 2) [landmark row, query keypoint]
    inlier_mask: np.ndarray | None = None
    match_similarity: np.ndarray | None = None  # (K,) cosine of landmark vs query descriptor per match
    estimate: np.ndarray | None = None  # last PnP estimate even when the checks refused it
    # (K,) True for the matches that only the guided step found (by projection, not among the
    # descriptor-matched inliers); None when the pose did not take the guided step
    by_projection: np.ndarray | None = None
    # uncertainty of a successful pose (favormap.localize.refine.PoseCovariance; None when the final
    # weighted refinement is off)
    covariance: PoseCovariance | None = None
    camera: Camera | None = None  # the working pinhole camera of ``keypoints`` (undistorted, resized)
    # (K, 2) with LocalizeConfig.align: each match's keypoint as the final refinement used it, moved to
    # the mapping images (NaN where not an inlier or not aligned); None when alignment is off
    aligned: np.ndarray | None = None
    prior: np.ndarray | None = None  # the cam_from_world prior localization started from (None: without one)

    def to_json(self) -> dict:
        from ..geometry import inverse, rotmat_to_quat

        T = self.cam_from_world
        return {
            "success": bool(self.success),
            "message": self.message,
            "world_from_cam": inverse(T).tolist(),
            "cam_from_world": {"quaternion_xyzw": rotmat_to_quat(T[:3, :3]).tolist(), "translation": T[:3, 3].tolist()},
            "num_matches": int(self.num_matches),
            "num_inliers": int(self.num_inliers),
            "checks": {k: (round(v, 5) if isinstance(v, float) else v) for k, v in self.checks.items()},
            "uncertainty": None if self.covariance is None else self.covariance.to_json(),
            "iterations": [
                {
                    "kind": it.kind,
                    "cam_from_world": it.cam_from_world.tolist(),
                    "num_visible": it.num_visible,
                    "num_matches": it.num_matches,
                    "num_inliers": it.num_inliers,
                    "success": it.success,
                }
                for it in self.iterations
            ],
            "timings": {k: round(v, 5) for k, v in self.timings.items()},
            **({} if self.aligned is None else {"num_aligned": int(np.isfinite(self.aligned[:, 0]).sum())}),
        }


class Localizer:
    """Localizes query images against one map; keep it alive to localize many queries.

    ``descriptor_source`` overrides ``config.descriptors`` (e.g. nearest-view descriptors, which
    need data the map does not hold).

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
        thread_count(self.config.threads)  # when asked; after the extractor: sizes torch's pools too if it loaded torch
        if self.config.global_ratio is None:
            self.config = dataclasses.replace(self.config, global_ratio=self.extractor.policy.match_ratio)
        if self.config.match_threshold is None:
            self.config = dataclasses.replace(self.config, match_threshold=self.extractor.policy.match_threshold)
        self._map_sigma = None  # the map's mapping keypoint noise (px), computed on first use
        self._global = None  # (rows, unit mean descriptors) for prior-free matching, loaded on first use
        self._aligner = None  # favormap.localize.align.PlaneAligner (LocalizeConfig.align)
        if self.config.align is None:
            self.config = dataclasses.replace(self.config, align=map_aligns_by_default(self.map.provenance))
        if self.config.align:
            from .align import AlignConfig, PlaneAligner

            self._aligner = PlaneAligner(
                self.map, self.config.align_images, AlignConfig(references=self.config.align_references)
            )

    def close(self):
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
        the map itself is not changed)."""
        from .stream import Stream

        with Stream(self, first_prior, motion, refine_landmarks) as stream:
            for image in images:
                res = self.localize(image, stream.prior(), camera)
                stream.update(res)
                yield res

    def localize(
        self, image, prior_cam_from_world: np.ndarray | None = None, camera: Camera | None = None
    ) -> LocalizationResult:
        """Localize one query image. Without a prior, a coarse pose is found first by matching
        against all landmarks (see ``LocalizeConfig.global_fallback``)."""
        rebalance()  # pools sized by the rule follow the machine's load (favormap.threads; else a no-op)
        prior = None if prior_cam_from_world is None else self._check_prior(prior_cam_from_world)
        res = self._localize(image, prior, camera)
        res.prior = prior
        return res

    def _localize(self, image, prior: np.ndarray | None, camera: Camera | None) -> LocalizationResult:
        cfg = self.config
        t = {k: 0.0 for k in ("extraction", "visibility", "loading", "rendering", "matching", "pnp")}
        t0 = time.perf_counter()
        img, cam = self.prepare(image, camera)
        feats = self.extractor.extract(img)
        qdesc = np.asarray(feats.descriptors, np.float32)
        t["extraction"] = time.perf_counter() - t0
        q = _Query(feats, qdesc, cam)
        if cfg.align:
            q.image = img

        if prior is not None:
            res = self._refine(q, prior, [], t)
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

    def _pnp(self, q: _Query, points: np.ndarray, kp_idx: np.ndarray, t: dict, max_error_px: float | None = None):
        import pycolmap

        s = time.perf_counter()
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = max_error_px or self.config.ransac_max_error_px
        est.ransac.random_seed = self.config.seed
        ans = None
        if len(kp_idx) >= 4:
            ans = pycolmap.estimate_and_refine_absolute_pose(
                q.feats.keypoints[kp_idx].astype(np.float64),
                points.astype(np.float64),
                q.cam.to_pycolmap(),
                est,
                pycolmap.AbsolutePoseRefinementOptions(),
            )
        t["pnp"] += time.perf_counter() - s
        return ans

    def _confirm(self, q: _Query, res: LocalizationResult, start: np.ndarray, t: dict) -> None:
        """A successful ``res`` with fewer than ``SuccessChecks.confirm_below_inliers`` inliers is
        refused (in place; its pose becomes ``start``, where its iterations began) unless the
        prior-free estimate agrees with it. For a pose
        refined from that estimate this asks that the rendering iterations did not carry it away:
        with a looser ratio test (0.9) the fox's wallpaper query 0072 got a correct coarse pose (0.01
        units off) that the iterations moved 6.8 units, to the wallpaper's false consensus.

        The inliers counted are those of the last rendering iteration (matched by descriptor): the
        guided step's (matched by projection) grow with any pose that lines a repeated pattern up,
        and at a 3 px radius lifted both wallpaper queries above 100 inliers (two false successes)."""
        c = self.config.checks
        render = [it.num_inliers for it in res.iterations if it.kind == "render"]
        evidence = render[-1] if render else res.num_inliers
        if not res.success or evidence >= c.confirm_below_inliers:
            return
        coarse, it = self._global_pose(q, t)
        if coarse is not None:
            change = self._change(coarse, res.cam_from_world)
            res.checks["confirmation_change"], res.checks["confirmation_change_deg"] = change
            if not self._apart(change):
                return
            why = f"it lies {change[0]:.3f} x landmark depth, {change[1]:.2f} deg from the estimate without the prior"
        else:
            res.checks["confirmation_change"] = None
            why = f"without the prior no pose was found ({it.num_matches} matches, {it.num_inliers} inliers)"
        res.success, res.cam_from_world, res.covariance = False, start, None
        res.message = (
            f"the pose has only {evidence} inliers matched by descriptor (fewer than {c.confirm_below_inliers}) "
            f"and is not confirmed by matching against all landmarks: {why}"
        )

    def _global_pose(self, q: _Query, t: dict):
        """Coarse pose without a prior: mutual matches against every landmark's mean descriptor
        (computed once per query)."""
        if q.global_pose is None:
            q.global_pose = self._global_pose_uncached(q, t)
        return q.global_pose

    def _global_pose_uncached(self, q: _Query, t: dict):
        cfg = self.config
        s = time.perf_counter()
        if self._global is None:
            rows = np.arange(len(self.map))
            if len(rows) > cfg.global_max_landmarks:
                rows = np.sort(np.argsort(-self.map.track_length, kind="stable")[: cfg.global_max_landmarks])
            self._global = (rows, unit_rows(self.map.mean_descriptors(rows)))
        rows, d = self._global
        t["loading"] += time.perf_counter() - s
        s = time.perf_counter()
        m = match_descriptors(d, q.desc, cfg.match_threshold, mutual=True, ratio=cfg.global_ratio)
        t["matching"] += time.perf_counter() - s
        ans = self._pnp(q, self.positions[rows[m[:, 0]]], m[:, 1], t)
        n_in = int(ans["num_inliers"]) if ans is not None else 0
        ok = ans is not None and n_in >= cfg.checks.min_inliers
        pose = from_rigid3d(ans["cam_from_world"]) if ok else np.eye(4)
        return (pose if ok else None), IterationResult(pose, len(rows), len(m), n_in, ok, kind="global")

    def _visible(self, q: _Query, pose: np.ndarray, t: dict) -> np.ndarray:
        """Rows of the landmarks visible from ``pose`` (timed into ``t["visibility"]``)."""
        s = time.perf_counter()
        rows = visible_rows(
            self.index,
            q.cam,
            pose,
            self.map.view_dir,
            self.map.view_angle,
            self.map.depth_range,
            self.config.view_limits,
        )
        t["visibility"] += time.perf_counter() - s
        return rows

    def _refine(
        self, q: _Query, start: np.ndarray, iters: list[IterationResult], t: dict, anchor: np.ndarray | None = None
    ) -> LocalizationResult:
        """The rendering iterations from ``start``, then the guided step and the weighted refinement.

        ``anchor``: the prior-free estimate this refinement starts from. A pose with fewer than
        ``checks.confirm_below_inliers`` inliers that leaves it by more than
        ``checks.max_iteration_change`` would be refused by :meth:`_confirm`; for such a RANSAC
        solution the iteration takes the pose it rendered from, refined on its own inliers among the
        same matches (:meth:`_local_pnp`), instead. On the fox's wallpaper (query 0072 of the
        extrapolation split) RANSAC preferred a false consensus 6.8 units away (46 inliers at 4 px,
        on one repeated flower) to the correct pose (38 inliers at 4 px, 0.015 units from the truth):
        a larger inlier set is no evidence against a pose that the prior-free estimate confirms."""
        cfg = self.config
        pose = start
        last = None
        for _ in range(cfg.iterations):
            rows = self._visible(q, pose, t)
            rend, drows = describe(self.source, rows, pose, t)
            s = time.perf_counter()
            m = match_descriptors(rend, q.desc, cfg.match_threshold, cfg.mutual, cfg.ratio)
            m = distinct_pairs(m, drows, len(rows))
            sims = pair_similarity(rend, q.desc, m)
            t["matching"] += time.perf_counter() - s
            points = self.positions[drows[m[:, 0]]]
            ans = self._pnp(q, points, m[:, 1], t)
            if anchor is not None and ans is not None and self._leaves(ans, anchor):
                ans = self._local_pnp(q, pose, points, m[:, 1], t)
            n_in = int(ans["num_inliers"]) if ans is not None else 0
            ok = ans is not None and n_in >= cfg.checks.min_inliers
            new_pose = from_rigid3d(ans["cam_from_world"]) if ok else pose
            iters.append(IterationResult(new_pose, len(rows), len(m), n_in, ok))
            if not ok:
                break
            last = dict(
                matches=np.c_[drows[m[:, 0]], m[:, 1]], inliers=np.asarray(ans["inlier_mask"], bool), similarity=sims
            )
            dt, dr = pose_error(new_pose, pose)
            pose = new_pose
            if dt < cfg.stop_translation * self.scale and dr < cfg.stop_rotation_deg:
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

    def _change(self, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
        """How far apart two poses are: (translation / median landmark depth, rotation in deg)."""
        dt, dr = pose_error(a, b)
        return dt / self.scale, dr

    def _apart(self, change: tuple[float, float]) -> bool:
        """Whether a :meth:`_change` exceeds ``checks.max_iteration_change``."""
        limit = self.config.checks.max_iteration_change
        return change[0] > limit[0] or change[1] > limit[1]

    def _leaves(self, ans: dict, anchor: np.ndarray) -> bool:
        """Whether a PnP solution ``ans`` with few inliers lies beyond ``checks.max_iteration_change``
        of ``anchor`` (so that :meth:`_confirm` would refuse it)."""
        if int(ans["num_inliers"]) >= self.config.checks.confirm_below_inliers:
            return False
        return self._apart(self._change(from_rigid3d(ans["cam_from_world"]), anchor))

    def _local_pnp(self, q: _Query, pose: np.ndarray, points: np.ndarray, kp_idx: np.ndarray, t: dict, rounds: int = 3):
        """``pose`` refined on its own inliers (within ``ransac_max_error_px``) among the matches
        ``points`` <-> ``q.feats.keypoints[kp_idx]``, repeated until the inlier set stops changing: the
        local optimisation of RANSAC with ``pose`` as the only hypothesis. Returns a dict shaped as
        pycolmap's estimate (cam_from_world, num_inliers, inlier_mask), or None."""
        import pycolmap

        s = time.perf_counter()
        thr = self.config.ransac_max_error_px
        uv = q.feats.keypoints[kp_idx].astype(np.float64)
        X = np.asarray(points, np.float64)

        def inliers(T):
            p, z = project(q.cam.K, T, X, with_depth=True)
            return (z > 0) & (np.linalg.norm(p - uv, axis=1) < thr)

        out, mask = None, inliers(pose)
        for _ in range(rounds):
            if mask.sum() < 4:
                break
            r = pycolmap.refine_absolute_pose(to_rigid3d(pose), uv, X, mask, q.cam.to_pycolmap())
            if r is None:
                break
            pose = from_rigid3d(r["cam_from_world"])
            new = inliers(pose)
            out = dict(cam_from_world=r["cam_from_world"], num_inliers=int(new.sum()), inlier_mask=new)
            if np.array_equal(new, mask):
                break
            mask = new
        t["pnp"] += time.perf_counter() - s
        return out

    def _guided_steps(
        self, q: _Query, pose: np.ndarray, iters: list[IterationResult], found: dict, weighted: bool, t: dict
    ) -> tuple[dict, PoseCovariance | None]:
        """The guided step(s) after the rendering iterations, which matched ``found`` at ``pose``,
        then (``weighted``) the final weighted refinement: returns the final matches and the pose's
        covariance."""
        cfg = self.config
        last, gate, cov, fresh = found, None, None, False  # fresh: iters[-1] is refined on ``last``
        for r in range(cfg.guided_rounds):
            if weighted and (r > 0 or cfg.guided_gate_sigma > 0):  # search from the weighted pose
                if not fresh:
                    cov, fresh = self._weighted(q, iters[-1], last, t), True
                pose = iters[-1].cam_from_world
            if gate is None and cfg.guided_gate_sigma > 0:  # the gate's scale, from the descriptor inliers
                gate = self._gate_scale(q, pose, found)
            guided = self._guided(q, pose, iters, t, gate, found)
            if guided is None:  # the rendering iterations' (or the previous round's) estimate stays
                break
            last, fresh = guided, False
        if weighted and not fresh:
            cov = self._weighted(q, iters[-1], last, t)
        return last, cov

    def _landmark_sigma(self, rows: np.ndarray):
        """Mapping keypoint noise (px) behind landmarks ``rows``: LocalizeConfig.landmark_sigma_px."""
        v = self.config.landmark_sigma_px
        if v == "map":  # one figure for the map: the median over its landmarks
            if self._map_sigma is None:
                self._map_sigma = float(np.median(mapping_pixel_sigma(self.map))) if len(self.map) else 0.0
            return self._map_sigma
        if v == "landmark":  # each landmark's own
            return mapping_pixel_sigma(self.map, rows)
        return float(v)

    def _weighted(self, q: _Query, it: IterationResult, last: dict, t: dict) -> PoseCovariance | None:
        """Refine the pose of the final iteration ``it`` (in place) on its inliers, each weighted by
        its landmark's position uncertainty (favormap.localize.refine); returns its covariance."""
        cfg = self.config
        inl = last["matches"][last["inliers"]]
        X, kp = self.positions[inl[:, 0]], q.feats.keypoints[inl[:, 1]]
        if cfg.align:
            kp = self._aligned(q, it.cam_from_world, last, kp, t)
        s = time.perf_counter()
        Xcov = landmark_covariances(self.map, inl[:, 0], self._landmark_sigma(inl[:, 0]))
        ksig, scale = cfg.keypoint_sigma_px, None
        if cfg.refine_noise == "estimated" and len(inl) >= 6:
            it.cam_from_world, scale, ksig = estimate_noise(it.cam_from_world, X, kp, q.cam.K, Xcov, ksig)
            Xcov = scale * Xcov
        # the covariance counts the matches found by descriptor only: the guided step picks its extra
        # ones near where the pose predicts them, so their residuals are small by selection and their
        # errors follow the pose's (docs/implementation-notes.md, covariances)
        by_desc = last["by_descriptor"][last["inliers"]] if "by_descriptor" in last else None
        it.cam_from_world, cov = refine_pose(
            it.cam_from_world,
            X,
            kp,
            q.cam.K,
            Xcov,
            ksig,
            return_covariance=True,
            covariance_mask=by_desc if by_desc is not None and by_desc.sum() >= 6 else None,
        )
        if cov is not None and scale is not None:
            cov.landmark_scale, cov.keypoint_sigma_px = float(scale), float(np.median(ksig))
        t["pnp"] += time.perf_counter() - s
        return cov

    def _aligned(self, q: _Query, pose: np.ndarray, last: dict, kp: np.ndarray, t: dict) -> np.ndarray:
        """The keypoints ``kp`` of the inliers of ``last`` aligned to the mapping images
        (LocalizeConfig.align); ``q.aligned`` keeps them by match for the result."""
        from .align import blurred_gray

        s = time.perf_counter()
        if q.gray is None:
            q.gray = blurred_gray(q.image, self._aligner.config.sigma)
        idx = np.flatnonzero(last["inliers"])
        out, ok = self._aligner.align(q.gray, q.cam.K, pose, self.positions, last["matches"][idx, 0], kp)
        q.aligned = np.full((len(last["matches"]), 2), np.nan)
        q.aligned[idx[ok]] = out[ok]
        t["align"] = t.get("align", 0.0) + time.perf_counter() - s
        return out

    def _noise_model(self, q: _Query, pose: np.ndarray, rows: np.ndarray):
        """Predicted projections (N, 2) of landmarks ``rows`` from ``pose`` and the inverse
        covariances (N, 2, 2) of the weighted refinement's noise model there."""
        return projection_information(
            pose,
            self.positions[rows],
            q.cam.K,
            landmark_covariances(self.map, rows, self._landmark_sigma(rows)),
            self.config.keypoint_sigma_px,
        )

    def _gate_scale(self, q: _Query, pose: np.ndarray, last: dict) -> float:
        """Variance factor of the noise model as the descriptor inliers at ``pose`` show it: their
        median squared Mahalanobis residual over that of a chi-square(2) (2 ln 2), never below 1."""
        inl = last["matches"][last["inliers"]]
        uv, info = self._noise_model(q, pose, inl[:, 0])
        r = q.feats.keypoints[inl[:, 1]] - uv
        d2 = mahalanobis2(info, r)
        d2 = d2[np.isfinite(d2)]
        return max(float(np.median(d2)) / (2 * np.log(2)), 1.0) if len(d2) else 1.0

    def _guided(
        self,
        q: _Query,
        pose: np.ndarray,
        iters: list[IterationResult],
        t: dict,
        gate_scale: float | None = None,
        found: dict | None = None,
    ) -> dict | None:
        """Search by projection: each landmark visible from ``pose`` is matched to the most similar
        query keypoint within ``guided_radius_px`` of its projection (mutually, above the
        threshold) and, with ``gate_scale``, within ``guided_gate_sigma`` standard deviations of the
        noise model (times that variance factor); then PnP runs again with a tight threshold."""
        cfg = self.config
        rows = self._visible(q, pose, t)
        rend, drows = describe(self.source, rows, pose, t)
        s = time.perf_counter()
        gate = None
        if gate_scale:
            uv, info = self._noise_model(q, pose, drows)
            gate = (info / gate_scale, cfg.guided_gate_sigma**2)
        else:
            uv = project(q.cam.K, pose, self.positions[drows])
        m = match_near(
            rend,
            q.desc,
            uv,
            q.feats.keypoints,
            cfg.guided_radius_px,
            cfg.match_threshold if cfg.guided_match_threshold is None else cfg.guided_match_threshold,
            mutual=True,
            gate=gate,
        )
        m = distinct_pairs(m, drows, len(rows))
        idx, kidx = m[:, 0], m[:, 1]
        sims = pair_similarity(rend, q.desc, m)
        t["matching"] += time.perf_counter() - s
        ans = self._pnp(q, self.positions[drows[idx]], kidx, t, cfg.guided_ransac_px or cfg.guided_radius_px)
        n_in = int(ans["num_inliers"]) if ans is not None else 0
        ok = ans is not None and n_in >= cfg.checks.min_inliers
        iters.append(
            IterationResult(
                from_rigid3d(ans["cam_from_world"]) if ok else pose, len(rows), len(idx), n_in, ok, kind="guided"
            )
        )
        if not ok:
            iters.pop()  # keep the rendering iterations' estimate
            return None
        out = dict(matches=np.c_[drows[idx], kidx], inliers=np.asarray(ans["inlier_mask"], bool), similarity=sims)
        if found is not None:  # which pairs the rendering iteration had already matched by descriptor
            known = found["matches"][found["inliers"]]
            out["by_descriptor"] = pair_in(out["matches"], known)
        return out

    def _result(
        self, q: _Query, last: dict | None, iters: list[IterationResult], t: dict, start: np.ndarray, message: str = ""
    ) -> LocalizationResult:
        """Apply the success checks to the last iteration and assemble the result."""
        ok_iters = [it for it in iters if it.success]
        final = iters[-1]
        checks: dict = {}
        reason = message
        if not message:
            if not final.success:
                reason = (
                    f"too few inliers ({final.num_matches} matches, {final.num_inliers} inliers, {final.num_visible} "
                    f"visible landmarks; need {self.config.checks.min_inliers} inliers)"
                )
                if final.num_visible < self.config.checks.min_inliers:
                    reason += (
                        "; the prior sees almost none of the map's landmarks: is it world_from_cam in OpenCV "
                        "axes (x right, y down, z forward), in the map's frame?"
                    )
            else:
                checks, reason = self._checks(q, last, iters)
        success = not reason
        est = ok_iters[-1].cam_from_world if ok_iters else None
        aligned = q.aligned if last is not None and q.aligned is not None else None
        return LocalizationResult(
            success=success,
            cam_from_world=est if success else start,
            num_matches=final.num_matches,
            num_inliers=final.num_inliers,
            iterations=iters,
            timings=t,
            message=reason,
            checks=checks,
            keypoints=q.feats.keypoints,
            matches=None if last is None else last["matches"],
            inlier_mask=None if last is None else last["inliers"],
            match_similarity=None if last is None else last["similarity"],
            estimate=est,
            by_projection=None if last is None or "by_descriptor" not in last else ~last["by_descriptor"],
            camera=q.cam,
            aligned=aligned if aligned is not None and len(aligned) == len(last["matches"]) else None,
        )

    def _checks(self, q: _Query, last: dict, iters: list[IterationResult]) -> tuple[dict, str]:
        """Measured values of the success checks and the first one that fails ('' when all pass)."""
        c = self.config.checks
        final = iters[-1]
        pose = final.cam_from_world
        vals: dict = {"inliers": final.num_inliers, "inlier_ratio": final.num_inliers / max(final.num_matches, 1)}
        g = max([i for i, it in enumerate(iters) if it.kind == "global"], default=-1)
        render_iters = iters[g + 1 :]  # the refinement (render, guided) that gave this pose
        if len(render_iters) >= 2:
            change = self._change(render_iters[-1].cam_from_world, render_iters[-2].cam_from_world)
            vals["iteration_change"], vals["iteration_change_deg"] = change
        rows = last["matches"][last["inliers"], 0]
        vis = (
            visible_mask(
                self.positions[rows],
                q.cam,
                pose,
                self.map.view_dir[rows],
                self.map.view_angle[rows],
                self.map.depth_range[rows],
                self.config.view_limits,
            )
            if len(rows)
            else np.zeros(0, bool)
        )
        vals["visible_inliers"] = float(vis.mean()) if len(vis) else 0.0
        if vals["inlier_ratio"] < c.min_inlier_ratio:
            return (
                vals,
                f"low inlier ratio ({final.num_inliers} of {final.num_matches} matches; need {c.min_inlier_ratio:.0%})",
            )
        if len(render_iters) >= 2 and self._apart(change):
            return vals, (
                f"iterations disagree (last two estimates {vals['iteration_change']:.3f} x landmark depth, "
                f"{vals['iteration_change_deg']:.2f} deg apart)"
            )
        if vals["visible_inliers"] < c.min_visible_inliers:
            return vals, (
                f"only {vals['visible_inliers']:.0%} of the inlier landmarks are visible from the estimated pose "
                f"(need {c.min_visible_inliers:.0%})"
            )
        return vals, ""


@dataclass
class _Query:
    feats: object
    desc: np.ndarray  # (N, C) float32 unit descriptors
    cam: Camera
    global_pose: tuple | None = None  # (pose or None, IterationResult) of the prior-free step, once computed
    image: np.ndarray | None = None  # the working image (LocalizeConfig.align)
    gray: np.ndarray | None = None  # its blurred grey version, once aligned
    aligned: np.ndarray | None = None  # (K, 2) the last final refinement's aligned keypoints by match


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
