"""Evaluation of the localizer on a posed query sequence, with the mean-descriptor baseline."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import InputError
from ..geometry import camera_centers, perturb_pose, pose_error
from ..io import Sequence
from .localizer import LocalizationResult, Localizer

DEFAULT_THRESHOLDS = ((0.01, 1.0), (0.05, 5.0), (0.25, 10.0))


@dataclass
class EvalConfig:
    prior_mode: str = "noise"  # noise | nearest | constant
    noise: tuple[float, float] = (0.3, 10.0)  # translation (map units), rotation (deg)
    seed: int = 0
    thresholds: tuple = DEFAULT_THRESHOLDS
    baseline: bool = True


@dataclass
class QueryOutcome:
    name: str
    gt: np.ndarray
    prior: np.ndarray
    result: LocalizationResult


@dataclass
class EvalReport:
    method: str
    outcomes: list[QueryOutcome]
    iterations: int
    thresholds: tuple
    summary: dict = field(default_factory=dict)


def make_priors(queries: Sequence, map_cam_from_world: np.ndarray, cfg: EvalConfig) -> list[np.ndarray]:
    rng = np.random.default_rng(cfg.seed)
    gts = [f.cam_from_world for f in queries.frames]
    if cfg.prior_mode == "noise":
        return [perturb_pose(T, cfg.noise[0], cfg.noise[1], rng) for T in gts]
    if len(map_cam_from_world) == 0:
        raise InputError("the map has no frames to take priors from")
    if cfg.prior_mode == "nearest":
        cm = camera_centers(map_cam_from_world)
        return [map_cam_from_world[np.argmin(np.linalg.norm(cm - camera_centers(T), axis=1))] for T in gts]
    if cfg.prior_mode == "constant":
        return [map_cam_from_world[0] for _ in gts]
    raise InputError(f"unknown prior mode {cfg.prior_mode!r} (noise, nearest, constant)")


def summarize(outcomes: list[QueryOutcome], iterations: int, thresholds) -> dict:
    n = len(outcomes)
    per_iter = []
    for k in range(iterations):
        errs, inl = [], []
        for o in outcomes:
            its = o.result.iterations
            ok = [it for it in its[: k + 1] if it.success]
            pose = ok[-1].cam_from_world if ok else o.prior
            errs.append(pose_error(pose, o.gt))
            inl.append(its[min(k, len(its) - 1)].num_inliers if its else 0)
        errs = np.array(errs)
        per_iter.append({"iteration": k + 1, "median_translation": float(np.median(errs[:, 0])),
                         "median_rotation_deg": float(np.median(errs[:, 1])), "mean_inliers": float(np.mean(inl))})
    final = np.array([pose_error(o.result.cam_from_world, o.gt) for o in outcomes]).reshape(-1, 2)
    success = np.array([o.result.success for o in outcomes])
    recall = {f"{t:g}/{r:g}deg": float(np.mean(success & (final[:, 0] <= t) & (final[:, 1] <= r))) for t, r in thresholds}
    return {"queries": n, "success_rate": float(success.mean()) if n else 0.0, "per_iteration": per_iter, "recall": recall,
            "median_translation": float(np.median(final[:, 0])) if n else None,
            "median_rotation_deg": float(np.median(final[:, 1])) if n else None,
            "mean_time_s": float(np.mean([sum(o.result.timings.values()) for o in outcomes])) if n else None}


def evaluate(localizer: Localizer, queries: Sequence, cfg: EvalConfig = EvalConfig(), progress: Callable | None = None,
             on_query: Callable | None = None) -> list[EvalReport]:
    """Localize every query frame from its prior with rendered descriptors (and, when
    ``cfg.baseline``, with the mean observed descriptors on the same map)."""
    priors = make_priors(queries, localizer.map.cam_from_world, cfg)
    methods = ["rendered"] + (["mean"] if cfg.baseline else [])
    reports = []
    base_mode = localizer.config.descriptors
    try:
        for mi, method in enumerate(methods):
            localizer.config.descriptors = method
            outs = []
            for i, (fr, prior) in enumerate(zip(queries.frames, priors)):
                cam = queries.cameras[fr.camera_id]
                res = localizer.localize(fr.image_path, prior, cam)
                outs.append(QueryOutcome(fr.name, fr.cam_from_world, prior, res))
                if on_query:
                    on_query(method, i, outs[-1])
                if progress:
                    progress(f"eval {method}", i + 1, len(queries.frames))
            reports.append(EvalReport(method, outs, localizer.config.iterations, cfg.thresholds,
                                      summarize(outs, localizer.config.iterations, cfg.thresholds)))
    finally:
        localizer.config.descriptors = base_mode
    return reports


def format_table(reports: list[EvalReport]) -> str:
    """A table like the paper's supplementary tables, one block per method."""
    lines = []
    for rep in reports:
        s = rep.summary
        lines.append(f"{rep.method} descriptors: {s['queries']} queries, success {100 * s['success_rate']:.1f} %, "
                     f"mean time {s['mean_time_s']:.3f} s")
        lines.append(f"  {'iter':>4}  {'median t':>10}  {'median R (deg)':>14}  {'mean inliers':>12}")
        for it in s["per_iteration"]:
            lines.append(f"  {it['iteration']:>4}  {it['median_translation']:>10.4f}  {it['median_rotation_deg']:>14.3f}  {it['mean_inliers']:>12.1f}")
        lines.append("  recall: " + ", ".join(f"({k}) {100 * v:.1f} %" for k, v in s["recall"].items()))
    return "\n".join(lines)
