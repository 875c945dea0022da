"""Evaluation of localizers on posed query frames: priors, error statistics, false successes and
match diagnostics at the ground-truth pose. ``favormap eval`` and ``tools/bench_accuracy.py`` use it.

A *false success* is a query reported as localized whose error exceeds ``false_success`` (by
default 5 % of the scene extent or 5 degrees): the one kind of answer a robot cannot recover from.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers, perturb_pose, pose_error, project
from ..io import Sequence
from ..visibility import project_inside, visible_rows
from .descriptors import describe
from .localizer import Localizer
from .matching import match_descriptors

DEFAULT_THRESHOLDS = ((0.01, 1.0), (0.05, 5.0), (0.25, 10.0))
PRIOR_MODES = ("noise", "nearest", "constant", "none", "sequential", "stream")


class Result(Protocol):
    """What every evaluated localizer returns (LocalizationResult, BaselineResult)."""

    success: bool
    cam_from_world: np.ndarray
    num_inliers: int


@dataclass
class EvalConfig:
    prior_mode: str = "noise"  # noise | nearest | constant | none | sequential | stream
    noise: tuple[float, float] = (0.3, 10.0)  # translation (map units), rotation (deg)
    seed: int = 0
    thresholds: tuple = DEFAULT_THRESHOLDS
    methods: tuple[str, ...] = ("rendered", "mean")  # descriptor sources evaluated on the same map
    false_success: tuple[float, float] = (0.05, 5.0)  # (fraction of the scene extent, degrees)


@dataclass
class QueryOutcome:
    name: str
    gt: np.ndarray
    prior: np.ndarray | None
    result: Result
    seconds: float = 0.0
    diagnostics: dict = field(default_factory=dict)


@dataclass
class EvalReport:
    method: str
    outcomes: list[QueryOutcome]
    iterations: int
    thresholds: tuple
    summary: dict = field(default_factory=dict)


def make_priors(queries: Sequence, map_cam_from_world: np.ndarray, cfg: EvalConfig) -> list[np.ndarray | None]:
    """One prior per query frame: the ground truth moved by ``cfg.noise`` ('noise'), the nearest
    mapping frame ('nearest'), the first mapping frame ('constant') or no prior ('none'). With
    'sequential' the queries are a stream: the first has no prior and each next one takes its prior
    from the poses estimated before it (:class:`SequencePriors`), so these are all None; 'stream'
    also refines the landmarks from the frames localized so far (favormap.localize.stream)."""
    rng = np.random.default_rng(cfg.seed)
    gts = [f.cam_from_world for f in queries.frames]
    if cfg.prior_mode == "noise":
        return [perturb_pose(T, cfg.noise[0], cfg.noise[1], rng) for T in gts]
    if cfg.prior_mode in ("none", "sequential", "stream"):
        return [None for _ in gts]
    if len(map_cam_from_world) == 0:
        raise InputError("the map has no frames to take priors from")
    if cfg.prior_mode == "nearest":
        cm = camera_centers(map_cam_from_world)
        return [map_cam_from_world[np.argmin(np.linalg.norm(cm - camera_centers(T), axis=1))] for T in gts]
    if cfg.prior_mode == "constant":
        return [map_cam_from_world[0] for _ in gts]
    raise InputError(f"unknown prior mode {cfg.prior_mode!r} ({', '.join(PRIOR_MODES)})")


class SequencePriors:
    """The prior of each query in turn: the fixed ones of :func:`make_priors`, or, in the
    'sequential' and 'stream' modes, those of a :class:`favormap.localize.stream.Stream` of the
    queries (constant velocity; in 'stream' mode ``localizer``'s landmarks are also refined from the
    queries localized so far). ``prior(i)`` before query i, ``update(result)`` after it, ``close()``
    at the end."""

    def __init__(self, priors: list, prior_mode: str, localizer: Localizer | None = None):
        self.priors = priors
        self.stream = None
        if prior_mode in ("sequential", "stream"):
            if localizer is None:
                raise InputError(f"the {prior_mode!r} prior mode follows a localizer's estimates: give the localizer")
            from .stream import Stream

            self.stream = Stream(localizer, refine_landmarks=prior_mode == "stream")

    def prior(self, i: int) -> np.ndarray | None:
        return self.priors[i] if self.stream is None else self.stream.prior()

    def update(self, result) -> None:
        if self.stream is not None:
            self.stream.update(result)

    def close(self) -> None:
        if self.stream is not None:
            self.stream.close()


def scene_extent(points: np.ndarray) -> float:
    """Diagonal of the 5-95 % bounding box of the map's landmarks (scene units)."""
    if len(points) < 2:
        return 1.0
    lo, hi = np.percentile(points, [5, 95], axis=0)
    return float(np.linalg.norm(hi - lo))


def summarize(
    outcomes: list[QueryOutcome],
    iterations: int,
    thresholds,
    extent: float = 1.0,
    false_success: tuple[float, float] = (0.05, 5.0),
) -> dict:
    """Error statistics of one method; failed queries count with their (prior) pose in the medians."""
    n = len(outcomes)
    if n == 0:
        return {"queries": 0}
    per_iter = []
    for k in range(iterations):
        errs, inl = [], []
        for o in outcomes:
            its = [
                it for it in (getattr(o.result, "iterations", None) or []) if getattr(it, "kind", "render") == "render"
            ]
            ok = [it for it in its[: k + 1] if it.success]
            pose = ok[-1].cam_from_world if ok else o.result.cam_from_world
            errs.append(pose_error(pose, o.gt))
            inl.append(its[min(k, len(its) - 1)].num_inliers if its else o.result.num_inliers)
        errs = np.array(errs)
        per_iter.append(
            {
                "iteration": k + 1,
                "median_translation": float(np.median(errs[:, 0])),
                "median_rotation_deg": float(np.median(errs[:, 1])),
                "mean_inliers": float(np.mean(inl)),
            }
        )
    final = np.array([pose_error(o.result.cam_from_world, o.gt) for o in outcomes]).reshape(-1, 2)
    success = np.array([bool(o.result.success) for o in outcomes])
    wrong = (final[:, 0] > false_success[0] * extent) | (final[:, 1] > false_success[1])
    recall = {
        f"{t:g}/{r:g}deg": float(np.mean(success & (final[:, 0] <= t) & (final[:, 1] <= r))) for t, r in thresholds
    }
    loc = final[success]
    diag = [o.diagnostics for o in outcomes if o.diagnostics]

    def dmean(key):
        v = [d[key] for d in diag if d.get(key) is not None]
        return float(np.mean(v)) if v else None

    def localized_median(key):  # over the localized queries, where the caller computed ``key``
        v = [o.diagnostics[key] for o in outcomes if o.result.success and o.diagnostics.get(key) is not None]
        return float(np.median(v)) if v else None

    return {
        "queries": n,
        "localized": int(success.sum()),
        "success_rate": float(success.mean()),
        "false_successes": int((success & wrong).sum()),
        "median_translation": float(np.median(loc[:, 0])) if len(loc) else None,
        "p90_translation": float(np.percentile(loc[:, 0], 90)) if len(loc) else None,
        "median_translation_pct_extent": float(100 * np.median(loc[:, 0]) / extent) if len(loc) else None,
        "median_rotation_deg": float(np.median(loc[:, 1])) if len(loc) else None,
        "mean_inliers": float(np.mean([o.result.num_inliers for o in outcomes])),
        "per_iteration": per_iter,
        "recall": recall,
        "scene_extent": extent,
        "mean_time_s": float(np.mean([o.seconds for o in outcomes])),
        "match_precision": dmean("match_precision"),
        "keypoint_repeatability": dmean("keypoint_repeatability"),
        "median_noise_floor": localized_median("noise_floor"),  # pose_noise_floor
        "median_residual_px": localized_median("residual_px"),
        "median_nees": localized_median("nees"),  # error normalised by the reported covariance (pose_nees)
        "median_position_std": localized_median("position_std"),
    }


def _nearest_keypoint_distance(uv: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    if len(uv) == 0 or len(keypoints) == 0:
        return np.full(len(uv), np.inf)
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(keypoints, np.float64)).query(np.asarray(uv, np.float64))[0]


def diagnostics_from_matches(
    camera,
    gt: np.ndarray,
    points: np.ndarray,
    keypoints: np.ndarray,
    matched_points: np.ndarray,
    matched_keypoints: np.ndarray,
    radius_px: float = 2.0,
) -> dict:
    """Match precision (share of matches whose keypoint lies within ``radius_px`` of the matched
    point's projection at the ground-truth pose) and keypoint repeatability (share of the
    candidate ``points`` projecting inside the image that have a query keypoint within ``radius_px``)."""
    inside = project_inside(points, camera, gt) if len(points) else np.zeros(0, bool)
    uv = project(camera.K, gt, points[inside]) if inside.any() else np.zeros((0, 2))
    rep = _nearest_keypoint_distance(uv, keypoints)
    err = (
        np.linalg.norm(project(camera.K, gt, matched_points) - matched_keypoints, axis=1)
        if len(matched_points)
        else np.zeros(0)
    )
    return {
        "match_precision": float(np.mean(err <= radius_px)) if len(err) else None,
        "median_match_error_px": float(np.median(err)) if len(err) else None,
        "keypoint_repeatability": float(np.mean(rep <= radius_px)) if len(rep) else None,
        "diag_matches": int(len(err)),
        "diag_points": int(len(uv)),
    }


def pose_nees(result, gt: np.ndarray) -> float | None:
    """Camera-centre error of a successful result normalised by the covariance it reports
    (e^T C^-1 e; chi-square with 3 degrees of freedom, median 2.37, when that covariance is right;
    None without one)."""
    cov = getattr(result, "covariance", None)
    if not result.success or cov is None:
        return None
    off = camera_centers(result.cam_from_world) - camera_centers(gt)
    try:
        return float(off @ np.linalg.solve(cov.center, off))
    except np.linalg.LinAlgError:
        return None


def pose_noise_floor(
    camera, cam_from_world: np.ndarray, points: np.ndarray, keypoints: np.ndarray, samples: int = 30, seed: int = 0
) -> dict:
    """How far the pose estimated from these inlier correspondences moves under their own
    measurement noise alone: the ``points`` (K, 3) are projected at ``cam_from_world`` (the
    estimate), Gaussian noise of the correspondences' residual scale is added (per axis, from their
    median reprojection error), the pose is
    refined again (pycolmap, the localizer's refinement) from ``samples`` such noisy copies, and the
    median camera-centre displacement is reported. An estimate's error to the ground truth much
    larger than this floor comes from wrong or biased correspondences; an error near it can only
    shrink with more inliers or smaller residuals (the floor falls as residual / sqrt(inliers))."""
    import pycolmap

    from ..geometry import from_rigid3d, to_rigid3d

    X = np.asarray(points, np.float64).reshape(-1, 3)
    kp = np.asarray(keypoints, np.float64).reshape(-1, 2)
    if len(X) < 6:
        return {"noise_floor": None, "residual_px": None}
    uv = project(camera.K, cam_from_world, X)
    # robust per-axis sigma: the median residual norm of a 2-D Gaussian is sigma * sqrt(2 ln 2) (RANSAC
    # inliers up to its threshold would inflate an RMS)
    sigma = float(np.median(np.linalg.norm(uv - kp, axis=1)) / np.sqrt(2 * np.log(2)))
    rng = np.random.default_rng(seed)
    pc, start = camera.to_pycolmap(), to_rigid3d(cam_from_world)
    mask = np.ones(len(X), bool)
    moved = []
    for _ in range(samples):
        ans = pycolmap.refine_absolute_pose(start, uv + rng.normal(0.0, sigma, uv.shape), X, mask, pc)
        if ans is not None:
            moved.append(pose_error(from_rigid3d(ans["cam_from_world"]), cam_from_world)[0])
    return {"noise_floor": float(np.median(moved)) if moved else None, "residual_px": sigma}


def localizer_noise_floor(localizer: Localizer, image, camera, result) -> dict:
    """:func:`pose_noise_floor` of a successful localizer ``result`` (its final inliers), else {}."""
    if not result.success or result.matches is None or result.inlier_mask is None:
        return {}
    inl = np.asarray(result.matches, np.int64)[np.asarray(result.inlier_mask, bool)]
    return pose_noise_floor(
        localizer.prepare(image, camera)[1],
        result.cam_from_world,
        localizer.map.positions[inl[:, 0]],
        np.asarray(result.keypoints)[inl[:, 1]],
    )


def match_diagnostics(localizer: Localizer, image, camera, gt: np.ndarray, radius_px: float = 2.0) -> dict:
    """Diagnostics of the localizer's matching at the ground-truth pose: the landmarks visible from
    ``gt`` get their descriptors from the localizer's source at ``gt`` and are matched as in
    localization. ``gt`` is in the convention of the poses the map was built from, as priors are."""
    cfg = localizer.config
    gt = localizer.camera_pose(gt)
    img, cam = localizer.prepare(image, camera)
    feats = localizer.extractor.extract(img)
    rows = visible_rows(
        localizer.index,
        cam,
        gt,
        localizer.map.view_dir,
        localizer.map.view_angle,
        localizer.map.depth_range,
        cfg.view_limits,
    )
    desc, drows = describe(localizer.source, rows, gt, {})
    m = match_descriptors(desc, feats.descriptors, cfg.match_threshold, cfg.mutual, cfg.ratio)
    pos = localizer.map.positions
    return diagnostics_from_matches(
        cam, gt, pos[rows], feats.keypoints, pos[drows[m[:, 0]]], feats.keypoints[m[:, 1]], radius_px
    )


def evaluate(
    localizers: dict[str, Localizer],
    queries: Sequence,
    cfg: EvalConfig | None = None,
    progress: Callable | None = None,
    on_query: Callable | None = None,
    diagnostics: bool = False,
) -> list[EvalReport]:
    """Localize every query frame from its prior with each named localizer (e.g. one per
    descriptor source on the same map)."""
    import time

    cfg = EvalConfig() if cfg is None else cfg
    first = next(iter(localizers.values()))
    priors = make_priors(queries, first.map.rig_from_world, cfg)
    extent = scene_extent(first.map.positions)
    reports = []
    for method, loc in localizers.items():
        outs = []
        seq_priors = SequencePriors(priors, cfg.prior_mode, loc)
        try:
            for i, fr in enumerate(queries.frames):
                cam = queries.cameras[fr.camera_id]
                prior = seq_priors.prior(i)
                s = time.perf_counter()
                res = loc.localize(fr.image_path, prior, cam)
                seq_priors.update(res)
                o = QueryOutcome(fr.name, fr.cam_from_world, prior, res, time.perf_counter() - s)
                if diagnostics:
                    o.diagnostics = match_diagnostics(loc, fr.image_path, cam, fr.cam_from_world)
                    o.diagnostics.update(localizer_noise_floor(loc, fr.image_path, cam, res))
                o.diagnostics["nees"] = pose_nees(res, fr.cam_from_world)
                cov = getattr(res, "covariance", None)
                o.diagnostics["position_std"] = float(np.linalg.norm(cov.center_std)) if cov is not None else None
                outs.append(o)
                if on_query:
                    on_query(method, i, o)
                if progress:
                    progress(f"eval {method}", i + 1, len(queries.frames))
        finally:
            seq_priors.close()  # the localizer gets the map's landmarks back
        iters = loc.config.iterations
        reports.append(
            EvalReport(
                method, outs, iters, cfg.thresholds, summarize(outs, iters, cfg.thresholds, extent, cfg.false_success)
            )
        )
    return reports


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def format_table(reports: list[EvalReport]) -> str:
    """One block per method: summary line with units, then the error per iteration."""
    lines = []
    for rep in reports:
        s = rep.summary
        lines.append(
            f"{rep.method}: {s['localized']}/{s['queries']} localized, {s['false_successes']} false successes, "
            f"median {_fmt(s['median_translation'], '.4f')} units / {_fmt(s['median_rotation_deg'], '.3f')} deg "
            f"(p90 {_fmt(s['p90_translation'], '.4f')} units), {s['mean_time_s'] * 1000:.0f} ms/query"
        )
        lines.append(f"  {'iter':>4}  {'median t (units)':>16}  {'median R (deg)':>14}  {'mean inliers (count)':>20}")
        for it in s["per_iteration"]:
            lines.append(
                f"  {it['iteration']:>4}  {it['median_translation']:>16.4f}  {it['median_rotation_deg']:>14.3f}  "
                f"{it['mean_inliers']:>20.1f}"
            )
        lines.append("  recall (units/deg): " + ", ".join(f"({k}) {100 * v:.1f} %" for k, v in s["recall"].items()))
        if s.get("median_noise_floor") is not None:
            lines.append(
                f"  noise floor: {s['median_noise_floor']:.4f} units (median over the localized queries: how far "
                f"the pose moves under its inliers' own noise, {s['median_residual_px']:.2f} px; the error can "
                "only fall below about this with more inliers or smaller residuals)"
            )
        if s.get("median_position_std") is not None:
            lines.append(
                f"  reported uncertainty: median 1-sigma {s['median_position_std']:.4f} units; error / reported "
                f"(NEES) median {_fmt(s.get('median_nees'), '.1f')} (2.4 when the reported covariance is right)"
            )
    return "\n".join(lines)
