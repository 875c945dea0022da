"""The localizer's pose solvers: PnP-RANSAC (pycolmap's LO-RANSAC) on 2D-3D matches, and the local
refinement of a pose on its own inliers among them.

:class:`PoseSolving` is a part of :class:`favormap.localize.Localizer`: it uses the localizer's ``config``,
``_pool`` and ``_workers``."""

from __future__ import annotations

import time

import numpy as np

from ..geometry import from_rigid3d, project, to_rigid3d
from .result import Query

RANSAC_CONFIDENCE = 0.999  # PnP-RANSAC's confidence that a sampled hypothesis is all inliers (see _pnp)
# independent RANSAC runs that share that confidence (1 - (1 - RANSAC_CONFIDENCE) ** (1 / RANSAC_RUNS) each: together
# as likely to draw an all-inlier sample as one run, in about as many hypotheses), on the localizer's threads at once
RANSAC_RUNS = 2


class PoseSolving:
    def _pnp(
        self,
        q: Query,
        points: np.ndarray,
        kp_idx: np.ndarray,
        t: dict,
        max_error_px: float | None = None,
        refine: bool = True,
    ):
        """PnP-RANSAC (pycolmap's LO-RANSAC) on ``points`` <-> ``q.feats.keypoints[kp_idx]``: :data:`RANSAC_RUNS`
        runs with seeds ``config.seed``, ``config.seed + 1``, ..., side by side where the localizer has several
        threads (pycolmap's RANSAC is single-threaded and releases the GIL); the one with the most inliers wins (on
        a tie the smaller sum of squared inlier residuals, then the lower seed), so the result does not depend on
        the number of threads. With ``refine``, the pose is then refined on its inliers by pycolmap (the inlier set
        stays RANSAC's), as ``pycolmap.estimate_and_refine_absolute_pose`` does."""
        import pycolmap

        s = time.perf_counter()
        ans = None
        if len(kp_idx) >= 4:
            uv = q.feats.keypoints[kp_idx].astype(np.float64)
            X = np.asarray(points, np.float64)
            cam = q.cam.to_pycolmap()
            runs = [self._ransac_options(max_error_px, k) for k in range(RANSAC_RUNS)]
            if self._workers() > 1:
                pool = self._pool(RANSAC_RUNS - 1)
                jobs = [pool.submit(pycolmap.estimate_absolute_pose, uv, X, cam, o) for o in runs[1:]]
                found = [pycolmap.estimate_absolute_pose(uv, X, cam, runs[0])] + [j.result() for j in jobs]
            else:
                found = [pycolmap.estimate_absolute_pose(uv, X, cam, o) for o in runs]
            ans = self._best_run(q, found, uv, X)
            if ans is not None and refine:
                r = pycolmap.refine_absolute_pose(
                    ans["cam_from_world"], uv, X, ans["inlier_mask"], cam, pycolmap.AbsolutePoseRefinementOptions()
                )
                ans = None if r is None else dict(ans, cam_from_world=r["cam_from_world"])
        t["pnp"] += time.perf_counter() - s
        return ans

    def _ransac_options(self, max_error_px: float | None, run: int):
        """pycolmap's options for RANSAC run ``run`` of :meth:`_pnp`."""
        import pycolmap

        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = max_error_px or self.config.ransac_max_error_px
        seed = self.config.seed
        est.ransac.random_seed = seed + run if seed >= 0 else -1
        # COLMAP's defaults (confidence 0.99999, 3x the trials that confidence asks) run up to 10,000
        # hypotheses at the 10-30 % inlier ratios of real queries; the rendering iterations, the guided
        # step and the weighted refinement take the pose further, and with these the real-data suite
        # localizes the same queries as accurately (docs/accuracy.md) in half the PnP time
        est.ransac.confidence = 1.0 - (1.0 - RANSAC_CONFIDENCE) ** (1.0 / RANSAC_RUNS)
        est.ransac.dyn_num_trials_multiplier = 1.0
        return est

    def _best_run(self, q: Query, found: list, uv: np.ndarray, X: np.ndarray):
        """The RANSAC estimate with the most inliers among ``found`` (None where a run found nothing); on a tie,
        the smaller sum of squared reprojection errors over its inliers, then the earlier run."""
        found = [a for a in found if a is not None]
        if not found:
            return None
        top = max(int(a["num_inliers"]) for a in found)
        tied = [a for a in found if int(a["num_inliers"]) == top]
        if len(tied) == 1:
            return tied[0]
        return tied[int(np.argmin([self._inlier_cost(q, a, uv, X) for a in tied]))]

    @staticmethod
    def _inlier_cost(q: Query, ans, uv: np.ndarray, X: np.ndarray) -> float:
        mask = np.asarray(ans["inlier_mask"], bool)
        p = project(q.cam.K, from_rigid3d(ans["cam_from_world"]), X[mask])
        return float(np.sum((p - uv[mask]) ** 2))

    def _fit_tightly(self, q: Query, ans, points: np.ndarray, kp_idx: np.ndarray, t: dict):
        """A rendering iteration's RANSAC estimate ``ans`` (among the matches ``points`` <->
        ``q.feats.keypoints[kp_idx]``) refined on the matches within ``fit_max_error_px`` of it
        (:meth:`_local_pnp`), when at least ``checks.min_inliers`` lie that close; its inliers stay those
        within ``ransac_max_error_px`` of the refined pose. On maps whose own poses fit their images loosely
        the RANSAC threshold is wide (pose_noise_ransac times the map's epipolar limit): it keeps the
        consensus of blurred queries, whose correct matches lie several pixels off, but many poses explain
        about as many matches within it, so the estimate drifts among them from one iteration to the next.
        Within a few pixels only one of them fits."""
        cfg = self.config
        fit = cfg.fit_max_error_px
        if ans is None or not fit or fit >= cfg.ransac_max_error_px:
            return ans
        tight = self._local_pnp(q, from_rigid3d(ans["cam_from_world"]), points, kp_idx, t, max_error_px=fit)
        if tight is None or tight["num_inliers"] < cfg.checks.min_inliers:
            return ans
        s = time.perf_counter()
        uv = q.feats.keypoints[kp_idx]
        mask = self._within(q.cam.K, from_rigid3d(tight["cam_from_world"]), points, uv, cfg.ransac_max_error_px)
        t["pnp"] += time.perf_counter() - s
        return dict(tight, inlier_mask=mask, num_inliers=int(mask.sum()))

    @staticmethod
    def _within(
        K: np.ndarray, pose: np.ndarray, points: np.ndarray, keypoints: np.ndarray, max_error_px: float
    ) -> np.ndarray:
        """(N,) bool: which of the matches ``points`` (N, 3) <-> ``keypoints`` (N, 2) ``pose`` explains through
        pinhole ``K``: the point in front of the camera and projected within ``max_error_px`` of its keypoint."""
        p, z = project(K, pose, points, with_depth=True)
        return (z > 0) & (np.linalg.norm(p - keypoints, axis=1) < max_error_px)

    def _local_pnp(
        self,
        q: Query,
        pose: np.ndarray,
        points: np.ndarray,
        kp_idx: np.ndarray,
        t: dict,
        rounds: int = 3,
        max_error_px: float | None = None,
    ):
        """``pose`` refined on its own inliers (within ``max_error_px``, None: ``ransac_max_error_px``) among
        the matches ``points`` <-> ``q.feats.keypoints[kp_idx]``, repeated until the inlier set stops changing: the
        local optimisation of RANSAC with ``pose`` as the only hypothesis. Returns a dict shaped as
        pycolmap's estimate (cam_from_world, num_inliers, inlier_mask), or None."""
        import pycolmap

        s = time.perf_counter()
        thr = max_error_px or self.config.ransac_max_error_px
        uv = q.feats.keypoints[kp_idx].astype(np.float64)
        X = np.asarray(points, np.float64)

        def inliers(T):
            return self._within(q.cam.K, T, X, uv, thr)

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
