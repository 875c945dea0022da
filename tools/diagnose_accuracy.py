#!/usr/bin/env python3
"""Where favormap's pose error comes from on a split, side by side with the structure baseline.

For each split (the splits of tools/bench_accuracy.py) a favormap map and the pycolmap-SIFT baseline
are built from the mapping frames (the favormap map kept in --workdir and reused when its settings
match), every query is localized by both (favormap from the benchmark's noise priors, the baseline
without a prior, RANSAC seed 0) and the final inlier correspondences of each are examined:

  a) landmarks: the reprojection error of each inlier's 3D point at the query's ground-truth pose
     (median, p90, share above 2 px), next to the same points' errors in the mapping frames they
     were triangulated from; and binned by track length, triangulation angle (twice the largest
     angle of one of the point's mapping rays from their mean ray) and the point's depth in the
     query over the query's median inlier depth. Only the localized queries count here.
  b) per query: inliers, the grid cells of the image they cover (8 x 6), the inlier residuals at the
     ground-truth pose and at the estimated pose, the pose error, the pose of a plain (unweighted)
     non-linear refinement of the same inliers started from the estimate, the prior's distance and
     the cosine between the prior's offset and the estimate's offset from the ground truth (near 1:
     the estimate leans towards the prior).
  c) an oracle bound: LO-RANSAC PnP on only the inliers whose point lies within --oracle-px of its
     keypoint at the ground-truth pose. The pose's error left then is what the remaining
     correspondences' noise allows; the step from the method's own error to it is what the
     rejected (inaccurate) points cost.

Residuals at the ground-truth pose contain the query keypoint's own noise and the ground truth's
error as well as the 3D point's error; the mapping-frame residuals bound the keypoint noise.

    python tools/diagnose_accuracy.py --splits cup-holdout,office-holdout
    python tools/diagnose_accuracy.py --splits cup-holdout --json diag.json --reuse
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_accuracy as bench  # noqa: E402  (the splits, map builds and localizer settings of the benchmark)

GRID = (8, 6)  # image cells for the inliers' coverage
LENGTH_BINS = ((2, 3), (3, 4), (4, 6), (6, 10), (10, 10_000))
ANGLE_BINS = ((0, 2), (2, 5), (5, 10), (10, 20), (20, 180))
DEPTH_BINS = ((0, 0.7), (0.7, 1.0), (1.0, 1.4), (1.4, 1e9))


@dataclasses.dataclass
class PointSet:
    """One method's 3D points and what they were triangulated from (the mapping frames)."""

    positions: np.ndarray  # (P, 3) world
    track_length: np.ndarray  # (P,)
    angle_deg: np.ndarray  # (P,) triangulation angle: twice the largest angle of a viewing ray from the mean ray
    mapping_error_px: np.ndarray  # (O,) reprojection error of every mapping observation
    mapping_point: np.ndarray  # (O,) point of each observation


@dataclasses.dataclass
class QueryFit:
    """One method's final correspondences for one query and what they say about its pose."""

    name: str
    success: bool
    t_err: float
    r_err_deg: float
    inliers: int
    cells: int  # GRID cells holding an inlier keypoint
    gt_px: np.ndarray  # (I,) inlier residuals at the ground-truth pose
    est_px: np.ndarray  # (I,) ... at the estimated pose
    points: np.ndarray  # (I,) point rows of the inliers
    keypoints: np.ndarray  # (I, 2) their query keypoints (working image, px)
    uv_gt: np.ndarray  # (I, 2) their points' projections at the ground-truth pose
    by_projection: np.ndarray  # (I,) bool: found by the guided step's search by projection, not by descriptor
    gt: np.ndarray  # (4, 4) the ground-truth cam_from_world
    est: np.ndarray  # (4, 4) the estimate
    K: np.ndarray  # (3, 3) the working pinhole intrinsics
    depth_ratio: np.ndarray  # (I,) depth in the query at the ground truth over the median inlier depth
    plain_t_err: float  # the same inliers, unweighted Levenberg-Marquardt from the estimate
    oracle: dict  # px threshold -> (inliers kept, translation error, rotation error)
    prior_t: float | None = None
    prior_r_deg: float | None = None
    prior_cos: float | None = None  # cos(estimate - truth, prior - truth) of the camera centres


def point_set(positions, obs_point, obs_frame, obs_xy, cam_from_world, K) -> PointSet:
    """A PointSet from observations (point row, frame row, pixel) and per-frame poses (F,4,4) and K (F,3,3)."""
    from favormap.geometry import camera_centers, project, view_geometry

    X = np.asarray(positions, np.float64)
    p, f = np.asarray(obs_point, np.int64), np.asarray(obs_frame, np.int64)
    uv = project(K[f], cam_from_world[f], X[p])
    err = np.linalg.norm(uv - np.asarray(obs_xy, np.float64), axis=1)
    _, amax, _ = view_geometry(X, p, camera_centers(cam_from_world)[f])
    return PointSet(X, np.bincount(p, minlength=len(X)), 2 * amax, err, p)


def favormap_points(m) -> PointSet:
    from favormap.io.images import working_camera

    li, fi, xy = m.tracks()
    K = np.stack([working_camera(m.cameras[int(c)], m.max_side).K for c in m.frame_camera_ids])
    return point_set(m.positions[:], li, fi, xy, np.asarray(m.cam_from_world, np.float64), K)


def baseline_points(b) -> PointSet:
    t = b.tracks
    return point_set(b.points3d, t.point, t.frame, t.xy, t.cam_from_world, t.K)


def _pose(ans) -> np.ndarray | None:
    from favormap.geometry import from_rigid3d

    return None if ans is None else from_rigid3d(ans["cam_from_world"])


def fit_query(name, gt, res, pts: PointSet, oracle_px, prior=None) -> QueryFit:
    """The QueryFit of a localization result ``res`` (favormap's or the baseline's: keypoints,
    matches [point, keypoint], inlier_mask, camera, cam_from_world) against the truth ``gt``."""
    import pycolmap

    from favormap.geometry import camera_centers, pose_error, project, to_rigid3d

    est = getattr(res, "estimate", None)
    est = res.cam_from_world if est is None else est
    mm = np.zeros((0, 2), np.int64) if res.matches is None else np.asarray(res.matches, np.int64).reshape(-1, 2)
    inl = mm[np.asarray(res.inlier_mask, bool)] if len(mm) else mm
    X, kp = pts.positions[inl[:, 0]], np.asarray(res.keypoints, np.float64)[inl[:, 1]]
    cam = res.camera
    K = cam.K
    proj = getattr(res, "by_projection", None)
    proj = np.zeros(len(inl), bool) if proj is None else np.asarray(proj, bool)[np.asarray(res.inlier_mask, bool)]
    uv_gt, z_gt = project(K, gt, X, with_depth=True)
    gt_px = np.linalg.norm(uv_gt - kp, axis=1)
    est_px = np.linalg.norm(project(K, est, X) - kp, axis=1)
    dt, dr = pose_error(est, gt)
    cell = np.floor(kp / [cam.width / GRID[0], cam.height / GRID[1]]).astype(np.int64)
    cells = len(np.unique(cell[:, 0] * 1000 + cell[:, 1])) if len(kp) else 0
    plain = np.nan
    if len(X) >= 6:
        ans = pycolmap.refine_absolute_pose(to_rigid3d(est), kp, X, np.ones(len(X), bool), cam.to_pycolmap())
        T = _pose(ans)
        plain = np.nan if T is None else pose_error(T, gt)[0]
    oracle = {}
    for px in oracle_px:
        keep = gt_px < px
        T = None
        if keep.sum() >= 6:
            opts = pycolmap.AbsolutePoseEstimationOptions()
            opts.ransac.max_error = 4.0
            T = _pose(pycolmap.estimate_and_refine_absolute_pose(kp[keep], X[keep], cam.to_pycolmap(), opts))
        oracle[px] = (int(keep.sum()), *(pose_error(T, gt) if T is not None else (np.nan, np.nan)))
    out = QueryFit(
        name,
        bool(res.success),
        dt,
        dr,
        len(inl),
        cells,
        gt_px,
        est_px,
        inl[:, 0],
        kp,
        uv_gt,
        proj,
        np.asarray(gt, np.float64),
        np.asarray(est, np.float64),
        K,
        z_gt / max(float(np.median(z_gt)), 1e-12) if len(z_gt) else z_gt,
        plain,
        oracle,
    )
    if prior is not None:
        out.prior_t, out.prior_r_deg = pose_error(prior, gt)
        c = camera_centers(gt)
        a, b = camera_centers(est) - c, camera_centers(prior) - c
        out.prior_cos = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    return out


def _stats(v: np.ndarray) -> dict:
    v = np.asarray(v, np.float64)
    if not len(v):
        return {"n": 0}
    return {
        "n": int(len(v)),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "over_2px": float(np.mean(v > 2.0)),
    }


def landmark_summary(fits: list[QueryFit], pts: PointSet) -> dict:
    """(a): the inliers' residuals at the ground truth over all queries, the same points' residuals in
    their mapping frames, and the ground-truth residuals per bin of track length, angle and depth."""
    fits = [f for f in fits if f.success]
    gt = np.concatenate([f.gt_px for f in fits]) if fits else np.zeros(0)
    rows = np.concatenate([f.points for f in fits]).astype(np.int64) if fits else np.zeros(0, np.int64)
    depth = np.concatenate([f.depth_ratio for f in fits]) if fits else np.zeros(0)
    proj = np.concatenate([f.by_projection for f in fits]) if fits else np.zeros(0, bool)
    est = np.concatenate([f.est_px for f in fits]) if fits else np.zeros(0)
    used = np.isin(pts.mapping_point, np.unique(rows))
    out = {
        "points": int(len(pts.positions)),
        "query_gt": _stats(gt),
        # keypoint minus projection at the truth, per axis: a shift shared by every keypoint of an extractor
        "query_gt_offset_px": np.median(np.concatenate([f.keypoints - f.uv_gt for f in fits]), axis=0).tolist()
        if fits
        else None,
        "mapping_all": _stats(pts.mapping_error_px),
        "query_gt_by_descriptor": _stats(gt[~proj]),
        "query_gt_by_projection": _stats(gt[proj]),
        "query_est_by_descriptor": _stats(est[~proj]),
        "query_est_by_projection": _stats(est[proj]),
        "mapping_of_inliers": _stats(pts.mapping_error_px[used]),
        "median_track_length_of_inliers": float(np.median(pts.track_length[rows])) if len(rows) else None,
        "median_angle_of_inliers_deg": float(np.median(pts.angle_deg[rows])) if len(rows) else None,
    }
    for key, val, bins in (
        ("by_track_length", pts.track_length[rows], LENGTH_BINS),
        ("by_angle_deg", pts.angle_deg[rows], ANGLE_BINS),
        ("by_depth_ratio", depth, DEPTH_BINS),
    ):
        out[key] = {f"{lo:g}-{hi:g}": _stats(gt[(val >= lo) & (val < hi)]) for lo, hi in bins}
    return out


def common_inliers(fav: list[QueryFit], bas: list[QueryFit], radius_px: float = 0.5) -> dict:
    """Inliers of both methods at (nearly) the same query keypoint: there the keypoint noise is shared, so
    the difference of their residuals at the ground truth is the difference of their 3D points."""
    rf, rb, dk, dp = [], [], [], []
    for a, b in zip(fav, bas):
        if not (a.success and b.success and len(a.keypoints) and len(b.keypoints)):
            continue
        d = np.linalg.norm(a.keypoints[:, None] - b.keypoints[None], axis=2)
        j = d.argmin(axis=1)
        ok = d[np.arange(len(j)), j] < radius_px
        rf.append(a.gt_px[ok])
        rb.append(b.gt_px[j[ok]])
        dk.append(d[np.arange(len(j)), j][ok])
        dp.append(np.linalg.norm(a.uv_gt[ok] - b.uv_gt[j[ok]], axis=1))
    if not rf or not sum(len(v) for v in rf):
        return {"pairs": 0, "radius_px": radius_px}
    rf, rb, dk, dp = (np.concatenate(v) for v in (rf, rb, dk, dp))
    return {
        "radius_px": radius_px,
        "pairs": int(len(rf)),
        "favormap_median_px": float(np.median(rf)),
        "baseline_median_px": float(np.median(rb)),
        "favormap_p90_px": float(np.percentile(rf, 90)),
        "baseline_p90_px": float(np.percentile(rb, 90)),
        "keypoint_offset_median_px": float(np.median(dk)),
        "point_offset_median_px": float(np.median(dp)),
    }


def uncertainty_calibration(fits: list[QueryFit], m) -> dict:
    """How well favormap's landmark uncertainty (what its final refinement weighs each inlier by) ranks
    the inliers' errors at the truth: the residual per quartile of the projected standard deviation
    (each landmark's own mapping noise, ``landmark_sigma_px="landmark"``, and the map's median, "map"),
    and per quartile of the landmark's own mean mapping reprojection error, with Spearman's rank
    correlations."""
    from favormap.localize.refine import landmark_covariances, mapping_pixel_sigma, projected_std

    fits = [f for f in fits if f.success and len(f.points)]
    if not fits:
        return {}
    gt = np.concatenate([f.gt_px for f in fits])
    sig_map = float(np.median(mapping_pixel_sigma(m)))
    keys = {"std_landmark_sigma": [], "std_map_sigma": [], "own_mapping_error": []}
    for f in fits:
        rows = f.points.astype(np.int64)
        X = np.asarray(m.positions[:], np.float64)[rows]
        keys["std_landmark_sigma"].append(
            projected_std(X, landmark_covariances(m, rows, mapping_pixel_sigma(m, rows)), f.gt, f.K)
        )
        keys["std_map_sigma"].append(projected_std(X, landmark_covariances(m, rows, sig_map), f.gt, f.K))
        keys["own_mapping_error"].append(np.asarray(m.reproj_error, np.float64)[rows])
    out = {}
    for k, v in keys.items():
        v = np.concatenate(v)
        q = np.percentile(v, [25, 50, 75])
        b = np.digitize(v, q)
        rank = np.argsort(np.argsort(v)), np.argsort(np.argsort(gt))
        out[k] = {
            "quartile_edges": q.tolist(),
            "median_gt_px": [float(np.median(gt[b == i])) for i in range(4)],
            "spearman": float(np.corrcoef(*rank)[0, 1]),
        }
    return out


REFINEMENTS = (
    "unweighted Cauchy 0.5 px",
    "unweighted least squares",
    "landmark covariances, Cauchy",
    "landmark covariances, least squares",
    "fitted noise model, Cauchy (the localizer's)",
    "fitted noise model, least squares",
    "map-median covariances fitted, Cauchy",
    "descriptor inliers only, fitted noise model, Cauchy",
)


def refinement_ablation(fits: list[QueryFit], m, keypoint_sigma_px: float = 0.5) -> dict:
    """favormap's final refinement taken apart: each localized query's final inliers refined again from
    its estimate with favormap's refine_pose under each model of REFINEMENTS; per model the median
    translation error and the geometric mean of its ratio to the localizer's own error."""
    from favormap.geometry import pose_error
    from favormap.localize.refine import estimate_noise, landmark_covariances, mapping_pixel_sigma, refine_pose

    fits = [f for f in fits if f.success and len(f.points) >= 6]
    sig_map = float(np.median(mapping_pixel_sigma(m)))
    errs = {k: [] for k in REFINEMENTS}
    scales = []
    for f in fits:
        rows = f.points.astype(np.int64)
        X, kp = np.asarray(m.positions[:], np.float64)[rows], f.keypoints
        cov = landmark_covariances(m, rows, mapping_pixel_sigma(m, rows))
        T, scale, ksig = estimate_noise(f.est, X, kp, f.K, cov, keypoint_sigma_px)
        Tm, scale_m, ksig_m = estimate_noise(f.est, X, kp, f.K, landmark_covariances(m, rows, sig_map))
        scales.append((scale, float(np.median(ksig))))
        d = ~f.by_projection
        Td = f.est
        if d.sum() >= 6:
            Td, scale_d, ksig_d = estimate_noise(f.est, X[d], kp[d], f.K, cov[d], keypoint_sigma_px)
            Td = refine_pose(Td, X[d], kp[d], f.K, scale_d * cov[d], ksig_d)
        poses = (
            refine_pose(f.est, X, kp, f.K, None, keypoint_sigma_px),
            refine_pose(f.est, X, kp, f.K, None, keypoint_sigma_px, loss_scale=1e9),
            refine_pose(f.est, X, kp, f.K, cov, keypoint_sigma_px),
            refine_pose(f.est, X, kp, f.K, cov, keypoint_sigma_px, loss_scale=1e9),
            refine_pose(T, X, kp, f.K, scale * cov, ksig),
            refine_pose(T, X, kp, f.K, scale * cov, ksig, loss_scale=1e9),
            refine_pose(Tm, X, kp, f.K, scale_m * landmark_covariances(m, rows, sig_map), ksig_m),
            Td,
        )
        for k, P in zip(REFINEMENTS, poses):
            errs[k].append(pose_error(P, f.gt)[0])
    own = np.array([f.t_err for f in fits])
    out = {
        k: {"median_t": float(np.median(v)), "ratio_to_localizer": _gmean_ratio(v, own)} for k, v in errs.items() if v
    }
    if scales:
        out["median_landmark_scale"] = float(np.median([s for s, _ in scales]))
        out["median_keypoint_sigma_px"] = float(np.median([k for _, k in scales]))
    return out


def query_row(f: QueryFit) -> dict:
    return {
        "name": f.name,
        "success": f.success,
        "t_err": f.t_err,
        "r_err_deg": f.r_err_deg,
        "inliers": f.inliers,
        "by_projection": int(f.by_projection.sum()),
        "cells": f.cells,
        "gt_px_median": float(np.median(f.gt_px)) if len(f.gt_px) else None,
        "est_px_median": float(np.median(f.est_px)) if len(f.est_px) else None,
        "plain_t_err": f.plain_t_err,
        "oracle": {str(k): list(v) for k, v in f.oracle.items()},
        "prior_t": f.prior_t,
        "prior_r_deg": f.prior_r_deg,
        "prior_cos": f.prior_cos,
    }


def localize_split(split, args) -> dict:
    """Build (or reuse) both maps of ``split``, localize its queries with both and examine the fits."""
    import dataclasses as dc

    from favormap.build import BuildConfig
    from favormap.localize import Localizer, make_source
    from favormap.localize.baseline import StructureBaseline
    from favormap.localize.evaluate import EvalConfig, make_priors
    from favormap.mapfile import Map

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    path, build_s = bench.build_or_load(split, workdir, BuildConfig(), args.reuse)
    m = Map.open(path)
    t = time.perf_counter()
    base = StructureBaseline.build(split.mapping, workdir=workdir / f"{split.files}_baseline")
    print(
        f"[{split.name}] map {len(m)} landmarks ({'reused' if build_s is None else f'{build_s:.0f} s'}), "
        f"baseline {len(base)} points ({time.perf_counter() - t:.0f} s), {len(split.queries)} queries",
        file=sys.stderr,
    )
    fpts, bpts = favormap_points(m), baseline_points(base)
    cfg = dc.replace(bench.localizer_config({}), descriptors="rendered")
    loc = Localizer(m, cfg, descriptor_source=make_source("rendered", m, cfg.device))
    priors = make_priors(split.queries, m.rig_from_world, EvalConfig(prior_mode="noise", seed=args.seed))
    fav, bas = [], []
    for fr, prior in zip(split.queries.frames, priors):
        cam = split.queries.cameras[fr.camera_id]
        res = loc.localize(fr.image_path, prior, cam)
        fav.append(fit_query(fr.name, fr.cam_from_world, res, fpts, args.oracle_px, prior))
        bres = base.localize(fr.image_path, cam)
        bas.append(fit_query(fr.name, fr.cam_from_world, bres, bpts, args.oracle_px))
    loc.close()
    out = {
        "split": split.name,
        "units": split.units,
        "path_extent": split.path_extent,
        "favormap": {"landmarks": landmark_summary(fav, fpts), "queries": [query_row(f) for f in fav]},
        "baseline": {"landmarks": landmark_summary(bas, bpts), "queries": [query_row(f) for f in bas]},
        "common": common_inliers(fav, bas),
        "calibration": uncertainty_calibration(fav, m),
        "refinements": refinement_ablation(fav, m, cfg.keypoint_sigma_px),
    }
    m.close()
    return out


def _f(v, spec=".2f") -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def _cell(s: dict) -> str:
    return "-" if not s.get("n") else f"{s['median']:.2f} / {s['p90']:.2f} / {100 * s['over_2px']:.0f}% ({s['n']})"


def _gmean_ratio(a, b) -> float | None:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    return float(np.exp(np.mean(np.log(a[ok] / b[ok])))) if ok.any() else None


def report(r: dict, oracle_px) -> str:
    """The tables of one split."""
    out = [f"## {r['split']}", ""]
    out += [
        "Landmarks (a): reprojection error (px) median / p90 / share > 2 px (count)",
        "",
        "| method | points | inliers at the truth (queries) | median keypoint - projection at the truth (x, y) | "
        "their mapping observations | all mapping observations | median track of inliers | "
        "median angle of inliers (deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in ("favormap", "baseline"):
        s = r[k]["landmarks"]
        out.append(
            f"| {k} | {s['points']} | {_cell(s['query_gt'])} | "
            + ("-" if s["query_gt_offset_px"] is None else "{:+.2f}, {:+.2f}".format(*s["query_gt_offset_px"]))
            + f" | {_cell(s['mapping_of_inliers'])} | "
            f"{_cell(s['mapping_all'])} | {_f(s['median_track_length_of_inliers'], '.0f')} | "
            f"{_f(s['median_angle_of_inliers_deg'], '.1f')} |"
        )
    s = r["favormap"]["landmarks"]
    out += [
        "",
        f"favormap inliers matched by descriptor, at the truth: {_cell(s['query_gt_by_descriptor'])}, at the "
        f"estimate: {_cell(s['query_est_by_descriptor'])}; found by the guided step's search by projection, at "
        f"the truth: {_cell(s['query_gt_by_projection'])}, at the estimate: {_cell(s['query_est_by_projection'])}",
    ]
    for key, title in (
        ("by_track_length", "track length"),
        ("by_angle_deg", "triangulation angle (deg)"),
        ("by_depth_ratio", "depth / the query's median inlier depth"),
    ):
        bins = list(r["favormap"]["landmarks"][key])
        out += ["", f"Inlier error at the truth by {title}", "", "| method | " + " | ".join(bins) + " |"]
        out.append("|---|" + "---|" * len(bins))
        for k in ("favormap", "baseline"):
            out.append(f"| {k} | " + " | ".join(_cell(r[k]["landmarks"][key][b]) for b in bins) + " |")
    fq, bq = r["favormap"]["queries"], r["baseline"]["queries"]
    out += [
        "",
        "Queries (b, c): favormap | baseline. t: error (units); px@gt / px@est: median inlier residual at the truth / "
        "at the estimate; plain: t of an unweighted refinement of the same inliers; "
        + ", ".join(f"oracle<{p:g}px: t (inliers kept)" for p in oracle_px)
        + "; prior t / deg / cos",
        "",
        "| query | t | inl | cells | px@gt | px@est | plain | "
        + " | ".join(f"oracle<{p:g}" for p in oracle_px)
        + " | prior | base t | inl | cells | px@gt | px@est | "
        + " | ".join(f"oracle<{p:g}" for p in oracle_px)
        + " |",
        "|---|" + "---|" * (10 + 2 * len(oracle_px)),
    ]

    def orc(q):
        return [f"{_f(q['oracle'][str(p)][1], '.4f')} ({q['oracle'][str(p)][0]})" for p in oracle_px]

    for a, b in zip(fq, bq):
        out.append(
            "| "
            + " | ".join(
                [
                    a["name"],
                    _f(a["t_err"], ".4f") + ("" if a["success"] else " x"),
                    str(a["inliers"]),
                    str(a["cells"]),
                    _f(a["gt_px_median"]),
                    _f(a["est_px_median"]),
                    _f(a["plain_t_err"], ".4f"),
                    *orc(a),
                    f"{_f(a['prior_t'], '.2f')} / {_f(a['prior_r_deg'], '.0f')} / {_f(a['prior_cos'])}",
                    _f(b["t_err"], ".4f") + ("" if b["success"] else " x"),
                    str(b["inliers"]),
                    str(b["cells"]),
                    _f(b["gt_px_median"]),
                    _f(b["est_px_median"]),
                    *orc(b),
                ]
            )
            + " |"
        )

    def med(qs, key, sub=None):
        v = [q[key] if sub is None else q[key][sub][1] for q in qs if q["success"]]
        return float(np.nanmedian(v)) if v else None

    t_f, t_b = [a["t_err"] for a in fq], [b["t_err"] for b in bq]

    def oracle_t(qs, p):
        return [q["oracle"][str(p)][1] for q in qs]

    orc_f = ", ".join(f"oracle<{p:g}px {_f(med(fq, 'oracle', str(p)), '.4f')}" for p in oracle_px)
    orc_b = ", ".join(f"oracle<{p:g}px {_f(med(bq, 'oracle', str(p)), '.4f')}" for p in oracle_px)
    orc_r = ", ".join(f"oracle<{p:g}px {_f(_gmean_ratio(oracle_t(fq, p), oracle_t(bq, p)), '.3f')}" for p in oracle_px)
    cos = [a["prior_cos"] for a in fq if a["prior_cos"] is not None]
    out += [
        "",
        f"Medians over the localized queries: favormap t {_f(med(fq, 't_err'), '.4f')}, plain refinement "
        f"{_f(med(fq, 'plain_t_err'), '.4f')}, {orc_f}; baseline t {_f(med(bq, 't_err'), '.4f')}, {orc_b}.",
        f"favormap / baseline (geometric mean over the queries): {_f(_gmean_ratio(t_f, t_b), '.3f')}; {orc_r}; "
        f"favormap / its plain refinement {_f(_gmean_ratio(t_f, [a['plain_t_err'] for a in fq]), '.3f')}; "
        f"median prior cos {_f(float(np.median(cos)) if cos else None)}.",
    ]
    c = r.get("common")
    if c:
        out += [
            "",
            f"Common inliers (a favormap and a baseline inlier keypoint within {c['radius_px']:g} px in the same "
            f"query, {c['pairs']} pairs): residual at the truth favormap {_f(c['favormap_median_px'])} / "
            f"baseline {_f(c['baseline_median_px'])} px median, {_f(c['favormap_p90_px'])} / "
            f"{_f(c['baseline_p90_px'])} p90; keypoint offset {_f(c['keypoint_offset_median_px'])} px median; "
            f"the two 3D points {_f(c['point_offset_median_px'])} px apart at the truth (median).",
        ]
    ref = r.get("refinements") or {}
    if ref:
        out += [
            "",
            "favormap's final inliers refined again from its estimate (median t; geometric mean of t over the "
            f"localizer's; fitted landmark scale {_f(ref.get('median_landmark_scale'))}, keypoint sigma "
            f"{_f(ref.get('median_keypoint_sigma_px'))} px, medians): "
            + "; ".join(
                f"{k} {_f(ref[k]['median_t'], '.4f')} ({_f(ref[k]['ratio_to_localizer'], '.3f')})"
                for k in REFINEMENTS
                if k in ref
            ),
            "",
        ]
    for k, v in (r.get("calibration") or {}).items():
        out.append(
            f"favormap inlier error at the truth by quartile of {k} (edges "
            + ", ".join(f"{e:.3g}" for e in v["quartile_edges"])
            + "): "
            + " / ".join(f"{x:.2f}" for x in v["median_gt_px"])
            + f" px, Spearman {v['spearman']:+.2f}"
        )
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default="cup-holdout,office-holdout", help="real splits of tools/bench_accuracy.py")
    ap.add_argument("--workdir", default="/tmp/favormap-diagnose-accuracy")
    ap.add_argument(
        "--reuse", action="store_true", help="reuse favormap maps in --workdir built with the same settings"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise priors")
    ap.add_argument("--oracle-px", default="1,2", help="ground-truth residual thresholds of the oracle PnP (px)")
    ap.add_argument(
        "--mapping-order",
        choices=("reader", "natural"),
        default="reader",
        help="the order of the mapping frames given to both builds: the reader's (the benchmark's) or by the "
        "numbers in their names (IMG_2 before IMG_10: the capture order of a video listed lexicographically)",
    )
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args()
    try:
        args.oracle_px = [float(x) for x in args.oracle_px.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--oracle-px {args.oracle_px!r}: expected numbers, e.g. 1,2")
    names = [s for s in args.splits.split(",") if s]
    unknown = [s for s in names if s not in bench.REAL_SPLITS and s not in bench.EXTRA_SPLITS]
    if unknown or not names:
        ap.error(f"unknown split(s) {unknown}; known: {list(bench.REAL_SPLITS)}")
    from favormap.errors import FavormapError

    splits = bench.real_splits(names)
    if args.mapping_order == "natural":  # the mapping frames in the order of their names' numbers
        for sp in splits:
            sp.mapping = sp.mapping.subset(bench._natural_order(sp.mapping))
            sp.map_name = f"{sp.name}-natural"
    if not splits:
        print(f"error: none of the splits' sets found under {bench.DATA}", file=sys.stderr)
        return 1
    results = []
    try:
        for sp in splits:
            results.append(localize_split(sp, args))
            print(report(results[-1], args.oracle_px) + "\n", flush=True)
    except FavormapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
