"""The localize / eval recording: each query image, its matches and the estimated, prior and
ground-truth poses on the ``query`` timeline, with per-method metrics."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr

from .. import geometry
from .base import (
    ALIGNED,
    GREY,
    GT,
    GUIDED,
    INLIER,
    OUTLIER,
    PRIOR,
    QUERY_IMAGE_SIDE,
    SERIES,
    RecordingBase,
    _guarded,
    _jpeg,
    _pinhole,
    _scaled_K,
    _transform,
    colormap,
)


@dataclass
class _QueryView:
    """What every entity group of one query's recording shares: its method's entity path and the
    displayed query image's camera, the final estimate and the keypoints."""

    method: str
    base: str  # world/query/<method>
    K: np.ndarray  # (3, 3) intrinsics of the displayed image
    width: int
    height: int
    scale: float  # displayed pixels per working pixel
    depth: float  # frustum depth
    cam_from_world: np.ndarray  # (4, 4) the final estimate
    keypoints: np.ndarray  # (N, 2) the query's keypoints in displayed pixels


@dataclass
class _QueryMatches:
    """A result's matches as the recording shows them; per-match arrays a result lacks (or whose length
    is not the matches') read as none."""

    pairs: np.ndarray  # (M, 2) landmark, keypoint
    inlier: np.ndarray  # (M,) bool
    guided: np.ndarray  # (M,) bool: found by projecting the landmark
    similarity: np.ndarray | None  # (M,) descriptor similarity

    @classmethod
    def of(cls, result) -> _QueryMatches:
        pairs = (
            np.zeros((0, 2), np.int64)
            if result.matches is None
            else np.asarray(result.matches, np.int64).reshape(-1, 2)
        )
        inl = np.zeros(len(pairs), bool)
        if result.inlier_mask is not None and len(result.inlier_mask) == len(pairs):
            inl = np.asarray(result.inlier_mask, bool)
        sim = getattr(result, "match_similarity", None)
        sim = None if sim is None or len(sim) != len(pairs) else np.asarray(sim, np.float64)
        guided = getattr(result, "by_projection", None)
        guided = np.zeros(len(pairs), bool) if guided is None or len(guided) != len(pairs) else np.asarray(guided, bool)
        return cls(pairs, inl, guided, sim)


class LocalizeLog(RecordingBase):
    """Each localized or evaluated query."""

    def _working_query(self, image, camera):
        """(working RGB image, working pinhole camera) exactly as the localizer prepares it."""
        from ..io import Camera, prepare_image, read_rgb

        img = image if isinstance(image, np.ndarray) else read_rgb(Path(image))
        h, w = img.shape[:2]
        cam = camera or self._map_camera
        if cam is None or ((w, h) != (cam.width, cam.height) and abs(w / h - cam.width / cam.height) > 0.01):
            f = float(max(w, h))
            cam = Camera("PINHOLE", w, h, [f, f, w / 2, h / 2])  # unknown camera: a plausible guess for display
        elif (w, h) != (cam.width, cam.height):
            cam = cam.scaled(w, h)
        return prepare_image(img, cam, self._map_max_side or None)

    @_guarded
    def log_localization(
        self,
        index: int,
        image,
        result,
        prior: np.ndarray,
        camera=None,
        gt: np.ndarray | None = None,
        method: str | None = None,
        positions: np.ndarray | None = None,
    ) -> None:
        """One query (timeline ``query``): prior, the pose after each iteration, the final pose with the
        query image, its keypoints and the matches (inliers green, outliers red), the inlier
        landmarks in 3D, per-match similarity when the result carries it, and per-query metrics.
        ``positions``: the landmark positions the localizer used (a stream's refined ones), when not
        the map's."""
        method = method or self.methods[0]
        self._at("query", index)
        img, cam = self._working_query(image, camera)
        enc, s, w, h = _jpeg(img, QUERY_IMAGE_SIDE)
        if prior is not None:  # localization without a prior starts from a global coarse pose
            prior = np.asarray(prior, np.float64)
        view = _QueryView(
            method=method,
            base=f"world/query/{method}",
            K=_scaled_K(cam.K, s),
            width=w,
            height=h,
            scale=s,
            depth=self._depth or 0.1,
            # the image's camera, in the frame of the map's landmarks (the landmarks are projected with it)
            cam_from_world=np.asarray(
                result.cam_from_world if result.image_cam_from_world is None else result.image_cam_from_world,
                np.float64,
            ),
            keypoints=np.zeros((0, 2)) if result.keypoints is None else np.asarray(result.keypoints, np.float64) * s,
        )
        its = list(result.iterations)
        self._log_reference_poses(view, prior, gt)
        self._log_iterations(view, prior, its)
        self._log_estimate(view, enc, result.success)
        matches = _QueryMatches.of(result)
        self._log_matches(view, matches, self._map_positions if positions is None else np.asarray(positions))
        self._log_aligned(view, result, len(matches.pairs))
        self._log_similarity(view, matches)
        cov = getattr(result, "covariance", None)
        self._log_uncertainty(view, cov)
        self._log_metrics(view, result, its[-1] if its else None, cov, matches.similarity)
        name = Path(str(image)).name if not isinstance(image, np.ndarray) else f"query {index}"
        self._log_status(view, name, result, prior, gt)

    def _log_reference_poses(self, view: _QueryView, prior: np.ndarray | None, gt: np.ndarray | None) -> None:
        """The prior and the ground-truth pose, each as a camera frustum."""
        K, w, h, depth = view.K, view.width, view.height, view.depth
        if prior is not None:
            self.rec.log("world/query/prior", _transform(prior), _pinhole(K, w, h, depth, PRIOR))
        if gt is not None:
            self.rec.log("world/query/gt", _transform(np.asarray(gt, np.float64)), _pinhole(K, w, h, depth, GT))

    def _log_iterations(self, view: _QueryView, prior: np.ndarray | None, its: list) -> None:
        """The pose after each iteration: the previous query's cleared, then the path prior -> it1 -> it2
        ... and a frustum each."""
        base = view.base
        self.rec.log(f"{base}/iterations", rr.Clear(recursive=True))
        path = ([prior] if prior is not None else []) + [np.asarray(it.cam_from_world) for it in its]
        centers = geometry.camera_centers(np.stack(path)) if path else np.zeros((0, 3))
        self.rec.log(
            f"{base}/iterations",
            rr.LineStrips3D(
                [centers], colors=[SERIES.get(view.method, (70, 130, 255))], radii=rr.Radius.ui_points(1.5)
            ),
        )
        for k, it in enumerate(its, 1):
            shade = int(80 + 150 * k / max(len(its), 1))
            self.rec.log(
                f"{base}/iterations/{k}",
                _transform(np.asarray(it.cam_from_world)),
                _pinhole(view.K, view.width, view.height, view.depth * 0.8, (60, 90, shade)),
            )

    def _log_estimate(self, view: _QueryView, image: rr.EncodedImage, success: bool) -> None:
        """The final estimate with the query image and its keypoints."""
        base = view.base
        self.rec.log(
            f"{base}/estimate",
            _transform(view.cam_from_world),
            _pinhole(view.K, view.width, view.height, view.depth, INLIER if success else OUTLIER),
        )
        self.rec.log(f"{base}/estimate/image", image)
        self.rec.log(
            f"{base}/estimate/image/keypoints",
            rr.Points2D(view.keypoints, colors=[GREY], radii=rr.Radius.ui_points(1.5)),
        )

    def _log_matches(self, view: _QueryView, matches: _QueryMatches, positions: np.ndarray | None) -> None:
        """The inlier landmarks in 3D and each match as a 2D line from its keypoint to its landmark's
        projection by the estimate: inliers (matched, or found by projection) and outliers."""
        base, pairs, inl, guided = view.base, matches.pairs, matches.inlier, matches.guided
        strips = {True: np.zeros((0, 2, 2)), False: np.zeros((0, 2, 2)), "guided": np.zeros((0, 2, 2))}
        if len(pairs) and positions is not None:
            uv, z = geometry.project(view.K, view.cam_from_world, positions[pairs[:, 0]], with_depth=True)
            front = z > 1e-9
            q = view.keypoints[pairs[:, 1]]
            for flag, sel in (
                (True, inl & ~guided & front),
                ("guided", inl & guided & front),
                (False, ~inl & front),
            ):
                strips[flag] = np.stack([q[sel], uv[sel]], 1)
            self.rec.log(
                f"{base}/inliers",
                rr.Points3D(positions[pairs[inl, 0]], colors=[INLIER], radii=rr.Radius.ui_points(4.0)),
            )
        else:
            self.rec.log(f"{base}/inliers", rr.Points3D(np.zeros((0, 3))))
        for name, key, color in (("inliers", True, INLIER), ("guided", "guided", GUIDED), ("outliers", False, OUTLIER)):
            self.rec.log(
                f"{base}/estimate/image/{name}",
                rr.LineStrips2D(strips[key], colors=[color], radii=rr.Radius.ui_points(1.0)),
            )

    def _log_aligned(self, view: _QueryView, result, n_matches: int) -> None:
        """Where the alignment moved the matched keypoints (``LocalizeConfig.align``), when it ran."""
        aligned = getattr(result, "aligned", None)
        if aligned is not None and len(aligned) == n_matches:
            moved = np.isfinite(aligned).all(1)
            self.rec.log(
                f"{view.base}/estimate/image/aligned",
                rr.Points2D(
                    np.asarray(aligned, np.float64)[moved] * view.scale,
                    colors=[ALIGNED],
                    radii=rr.Radius.ui_points(2.0),
                ),
            )

    def _log_similarity(self, view: _QueryView, matches: _QueryMatches) -> None:
        """Each match's descriptor similarity at its keypoint, when the result carries them."""
        sim = matches.similarity
        if sim is not None:
            self.rec.log(
                f"{view.base}/estimate/image/similarity",
                rr.Points2D(
                    view.keypoints[matches.pairs[:, 1]],
                    colors=colormap(sim, 0.5, 1.0),
                    radii=rr.Radius.ui_points(3.0),
                    labels=[f"{v:.2f}" for v in sim],
                    show_labels=False,
                ),
            )

    def _log_uncertainty(self, view: _QueryView, cov) -> None:
        """The pose's reported uncertainty: the camera centre's 3-sigma ellipsoid (world axes)."""
        if cov is None:
            self.rec.log(f"{view.base}/uncertainty", rr.Clear(recursive=False))
            return
        evals, evecs = np.linalg.eigh(np.asarray(cov.center, np.float64))
        if np.linalg.det(evecs) < 0:
            evecs[:, 0] = -evecs[:, 0]
        self.rec.log(
            f"{view.base}/uncertainty",
            rr.Ellipsoids3D(
                centers=[geometry.camera_centers(view.cam_from_world)],
                half_sizes=[3.0 * np.sqrt(np.clip(evals, 0, None))],
                quaternions=[rr.Quaternion(xyzw=geometry.rotmat_to_quat(evecs))],
                colors=[INLIER],
                labels=["3 sigma"],
            ),
        )

    def _log_metrics(self, view: _QueryView, result, last, cov, sim: np.ndarray | None) -> None:
        """The query's counts, time, position uncertainty and median match similarity as time series."""
        method, color = view.method, SERIES.get(view.method, (70, 130, 255))
        for name, val in (
            ("inliers", result.num_inliers),
            ("matches", result.num_matches),
            ("visible", last.num_visible if last else 0),
            ("time_ms", 1000 * sum(result.timings.values())),
            *([("position_std", float(np.linalg.norm(cov.center_std)))] if cov is not None else []),
        ):
            self._series(f"metrics/{name}/{method}", method, color)
            self.rec.log(f"metrics/{name}/{method}", rr.Scalars(float(val)))
        if sim is not None and len(sim):
            self._series(f"metrics/similarity/{method}", method, color)
            self.rec.log(f"metrics/similarity/{method}", rr.Scalars(float(np.median(sim))))

    def _log_status(self, view: _QueryView, name: str, result, prior: np.ndarray | None, gt) -> None:
        """The pose errors of the estimate and the prior against the ground truth (where known) as time
        series, and one text line of the query's outcome."""
        method, color = view.method, SERIES.get(view.method, (70, 130, 255))
        status = (
            f"localized, {result.num_inliers} inliers / {result.num_matches} matches"
            if result.success
            else f"NOT localized: {result.message}"
        )
        if gt is not None:
            dt, dr = geometry.pose_error(np.asarray(result.cam_from_world, np.float64), np.asarray(gt, np.float64))
            pt, pr = geometry.pose_error(prior, np.asarray(gt, np.float64)) if prior is not None else (None, None)
            for metric, val, prior_val in (("translation_error", dt, pt), ("rotation_error_deg", dr, pr)):
                self._series(f"metrics/{metric}/{method}", method, color)
                self.rec.log(f"metrics/{metric}/{method}", rr.Scalars(val))
                if prior_val is not None:
                    self._series(f"metrics/{metric}/prior", "prior", SERIES["prior"])
                    self.rec.log(f"metrics/{metric}/prior", rr.Scalars(prior_val))
            status += f"; error {dt:.4f} / {dr:.2f} deg" + (
                f" (prior {pt:.4f} / {pr:.2f} deg)" if pt is not None else " (no prior)"
            )
        self.rec.log(f"log/{method}", rr.TextLog(f"{name}: {status}", level="INFO" if result.success else "WARN"))

    @_guarded
    def log_refined_landmarks(self, index: int, positions: np.ndarray, map_positions: np.ndarray) -> None:
        """A stream's refined landmarks after query ``index`` (favormap.localize.stream): where they are
        now and the line from where the map put them."""
        self._at("query", index)
        rows = np.flatnonzero(np.any(positions != map_positions, axis=1))
        self.rec.log(
            "world/stream/refined", rr.Points3D(positions[rows], colors=[GUIDED], radii=rr.Radius.ui_points(3.0))
        )
        self.rec.log(
            "world/stream/refined/moves",
            rr.LineStrips3D(np.stack([map_positions[rows], positions[rows]], 1), colors=[GUIDED]),
        )
        self._series("metrics/refined_landmarks", "refined landmarks", GUIDED)
        self.rec.log("metrics/refined_landmarks", rr.Scalars(float(len(rows))))

    def log_eval_query(self, method: str, index: int, outcome, frame=None, camera=None) -> None:
        """One evaluated query (a ``QueryOutcome``): as :meth:`log_localization`, with the ground
        truth and the pose errors (final and prior) on the ``query`` timeline."""
        image = frame.image_path if frame is not None else outcome.name
        self.log_localization(index, image, outcome.result, outcome.prior, camera=camera, gt=outcome.gt, method=method)
