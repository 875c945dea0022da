"""The localizer's pose solvers: PnP-RANSAC (pycolmap's LO-RANSAC) on 2D-3D matches, and the local
refinement of a pose on its own inliers among them.

:class:`PoseSolving` is a part of :class:`favormap.localize.Localizer`: it uses the localizer's ``config``."""

from __future__ import annotations

import time

import numpy as np

from ..geometry import from_rigid3d, project, to_rigid3d
from .result import Query

RANSAC_CONFIDENCE = 0.999  # PnP-RANSAC's confidence that a sampled hypothesis is all inliers (see _pnp)


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
        """PnP-RANSAC (pycolmap's LO-RANSAC) on ``points`` <-> ``q.feats.keypoints[kp_idx]``; with ``refine``, the
        pose is then refined on the inliers by pycolmap (the inlier set stays RANSAC's)."""
        import pycolmap

        s = time.perf_counter()
        est = pycolmap.AbsolutePoseEstimationOptions()
        est.ransac.max_error = max_error_px or self.config.ransac_max_error_px
        est.ransac.random_seed = self.config.seed
        # COLMAP's defaults (confidence 0.99999, 3x the trials that confidence asks) run up to 10,000
        # hypotheses at the 10-30 % inlier ratios of real queries; the rendering iterations, the guided
        # step and the weighted refinement take the pose further, and with these the real-data suite
        # localizes the same queries as accurately (docs/accuracy.md) in half the PnP time
        est.ransac.confidence = RANSAC_CONFIDENCE
        est.ransac.dyn_num_trials_multiplier = 1.0
        ans = None
        if len(kp_idx) >= 4:
            args = (q.feats.keypoints[kp_idx].astype(np.float64), points.astype(np.float64), q.cam.to_pycolmap(), est)
            if refine:
                ans = pycolmap.estimate_and_refine_absolute_pose(*args, pycolmap.AbsolutePoseRefinementOptions())
            else:
                ans = pycolmap.estimate_absolute_pose(*args)
        t["pnp"] += time.perf_counter() - s
        return ans

    def _local_pnp(self, q: Query, pose: np.ndarray, points: np.ndarray, kp_idx: np.ndarray, t: dict, rounds: int = 3):
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
