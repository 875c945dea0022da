"""The localizer's last stages: the guided step (search by projection, then PnP) and the weighted
refinement of the final pose under the landmarks' uncertainty (favormap.localize.refine), with the optional
keypoint alignment (favormap.localize.align).

:class:`FinalRefinement` is a part of :class:`favormap.localize.Localizer`: it uses the localizer's
``config``, ``map``, ``positions``, ``source``, ``_aligner``, ``_map_sigma``, ``_map_focal`` and its
``_visible`` and ``_pnp`` steps."""

from __future__ import annotations

import time

import numpy as np

from ..geometry import from_rigid3d, project
from ..mapfile.model import map_epipolar_px
from .covariance import PoseCovariance
from .descriptors import describe
from .matching import distinct_pairs, match_near, pair_in, pair_similarity
from .refine import (
    estimate_noise,
    landmark_covariances,
    mahalanobis2,
    mapping_pixel_sigma,
    projection_information,
    refine_pose,
    working_focal,
)
from .result import IterationResult, Query


class FinalRefinement:
    def _guided_steps(
        self, q: Query, pose: np.ndarray, iters: list[IterationResult], found: dict, weighted: bool, t: dict
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

    def _landmark_covariances(self, rows: np.ndarray) -> np.ndarray:
        """Position covariances of landmarks ``rows`` under the mapping keypoint noise of
        LocalizeConfig.landmark_sigma_px (the map's working focal length computed once)."""
        if self._map_focal is None:
            self._map_focal = working_focal(self.map)
        return landmark_covariances(self.map, rows, self._landmark_sigma(rows), self._map_focal)

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

    def _weighted(self, q: Query, it: IterationResult, last: dict, t: dict) -> PoseCovariance | None:
        """Refine the pose of the final iteration ``it`` (in place) on its inliers, each weighted by
        its landmark's position uncertainty (favormap.localize.refine); returns its covariance."""
        cfg = self.config
        inl = last["matches"][last["inliers"]]
        X, kp = self.positions[inl[:, 0]], q.feats.keypoints[inl[:, 1]]
        if cfg.align:
            kp = self._aligned(q, it.cam_from_world, last, kp, t)
        s = time.perf_counter()
        Xcov = self._landmark_covariances(inl[:, 0])
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
        if cov is not None:
            self._add_map_pose_noise(cov, it.cam_from_world, X, q.cam.K)
        t["pnp"] += time.perf_counter() - s
        return cov

    def _add_map_pose_noise(self, cov: PoseCovariance, pose: np.ndarray, X: np.ndarray, K: np.ndarray) -> None:
        """Add to ``cov`` (in place) the error the map's own poses leave in any pose localized against it: the
        landmarks were triangulated from mapping poses that its build measured to fit their images to
        ``epipolar_median_px`` (the right tracking matches' median distance from their epipolar lines), so
        the map's frame is known to about that many pixels at the landmarks' depth, however many inliers a
        query has. Independent of the query's own error: the covariances add. Maps that do not record the
        figure add nothing."""
        px = map_epipolar_px(self.map.provenance, "median")
        if px is None or len(X) == 0:
            return
        depth = float(np.median(X @ pose[2, :3] + pose[2, 3]))
        angle = float(px) / float(np.mean(np.diag(K)[:2]))  # rad
        cov.center = cov.center + (angle * max(depth, 0.0)) ** 2 * np.eye(3)
        cov.rotation = cov.rotation + angle**2 * np.eye(3)

    def _aligned(self, q: Query, pose: np.ndarray, last: dict, kp: np.ndarray, t: dict) -> np.ndarray:
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

    def _noise_model(self, q: Query, pose: np.ndarray, rows: np.ndarray):
        """Predicted projections (N, 2) of landmarks ``rows`` from ``pose`` and the inverse
        covariances (N, 2, 2) of the weighted refinement's noise model there."""
        return projection_information(
            pose,
            self.positions[rows],
            q.cam.K,
            self._landmark_covariances(rows),
            self.config.keypoint_sigma_px,
        )

    def _gate_scale(self, q: Query, pose: np.ndarray, last: dict) -> float:
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
        q: Query,
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
        rows = self._visible(q.cam, pose, t)
        rend, drows = describe(self.source, rows, pose, t, q.seen)
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
        # the weighted refinement refines a guided pose on its inliers (the rendering iterations' poses are
        # refined by pycolmap: the next iteration renders from them)
        thr = cfg.guided_ransac_px or cfg.guided_radius_px
        ans = self._pnp(q, self.positions[drows[idx]], kidx, t, thr, refine=cfg.landmark_sigma_px == 0)
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
