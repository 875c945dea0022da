"""Running the benchmark on a split: the localizer variants (VARIANTS, DEFAULT_VARIANTS, localizer_config), the
map builds and their reuse in --workdir (build_key, same_build, build_or_load), favormap's and the baseline's
localization of every query (run_split, run_favormap, run_baseline; a query's result the median over noise priors
or RANSAC seeds: median_run, median_over_priors, median_over_seeds), and what each run records: the summary row
of a (split, prior, method) with its angle bins (record) and each query's outcome (per_query)."""

from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

from .report import fmt_row
from .splits import ANGLE_BINS, Split

# localizer variants on the same map: name -> (descriptor source, LocalizeConfig overrides)
VARIANTS = {
    "rendered": ("rendered", {}),
    "mean": ("mean", {}),
    "nearest-view": ("nearest", {}),
    # the inliers' keypoints aligned to the mapping images through the landmark's plane before the final
    # refinement (LocalizeConfig.align, favormap.localize.align)
    "rendered align": ("rendered", {"align": True}),
    "mean align": ("mean", {"align": True}),
    "nearest-view align": ("nearest", {"align": True}),
    "rendered+nearest-view": ("rendered+nearest", {}),
    # each inlier aligned to its landmark's 3 / 5 mapping frames nearest in direction, averaged
    # (LocalizeConfig.align_references)
    "rendered align refs-3": ("rendered", {"align": True, "align_references": 3}),
    "mean align refs-3": ("mean", {"align": True, "align_references": 3}),
    "rendered align refs-5": ("rendered", {"align": True, "align_references": 5}),
    "mean align refs-5": ("mean", {"align": True, "align_references": 5}),
    # more rendering iterations for view-dependent descriptors (DISK), whose first iteration renders at
    # the prior's viewpoint
    "rendered 5-iterations": ("rendered", {"iterations": 5}),
    "rendered align 5-iterations": ("rendered", {"align": True, "iterations": 5}),
    "mean align 5-iterations": ("mean", {"align": True, "iterations": 5}),
    "rendered align 5-iterations stop-1%": ("rendered", {"align": True, "iterations": 5, "stop_change": 0.01}),
    "rendered 8px no-mutual (old default)": (
        "rendered",
        {"ransac_max_error_px": 8.0, "mutual": False, "ratio": 1.0, "landmark_sigma_px": 0, "guided_radius_px": 0},
    ),
    "rendered 2px": ("rendered", {"ransac_max_error_px": 2.0}),
    # the PnP-RANSAC threshold of maps whose poses fit their images loosely (7-Scenes, TUM: 1.5x the epipolar
    # limit by default) held at 4 / 6 px, or at 1.0x that limit
    "rendered 4px": ("rendered", {"ransac_max_error_px": 4.0}),
    "rendered 6px": ("rendered", {"ransac_max_error_px": 6.0}),
    "rendered epipolar-1x": ("rendered", {"pose_noise_ransac": 1.0}),
    "rendered no-fit": ("rendered", {"fit_max_error_px": None}),
    "rendered ratio-0.9": ("rendered", {"ratio": 0.9}),
    "rendered no-ratio": ("rendered", {"ratio": 1.0}),
    "rendered ratio-0.8": ("rendered", {"ratio": 0.8}),
    # the guided step (LocalizeConfig.guided_*; default: gated at 3 sigma within 8 px, for poses with
    # fewer than 400 descriptor inliers): off, for every pose, ungated at
    # 3 px (an earlier option), and other gates
    "rendered no-guided": ("rendered", {"guided_radius_px": 0}),
    "rendered gated every pose": ("rendered", {"guided_below_inliers": None}),
    "rendered guided-3px": (
        "rendered",
        {"guided_radius_px": 3.0, "guided_ransac_px": 3.0, "guided_gate_sigma": 0, "guided_below_inliers": None},
    ),
    "rendered gated-2sigma every pose": ("rendered", {"guided_gate_sigma": 2.0, "guided_below_inliers": None}),
    "rendered gated-3sigma-4px every pose": ("rendered", {"guided_radius_px": 4.0, "guided_below_inliers": None}),
    "rendered gated below-200": ("rendered", {"guided_below_inliers": 200}),
    # the guided step's PnP at the rendering iterations' 4 px instead of its 8 px search radius
    "rendered guided-ransac-4px": ("rendered", {"guided_ransac_px": 4.0}),
    "rendered gated 2-rounds": ("rendered", {"guided_rounds": 2}),
    "rendered gated cos-0.6": ("rendered", {"guided_match_threshold": 0.6}),
    "rendered gated cos-0.5": ("rendered", {"guided_match_threshold": 0.5}),
    "rendered gated cos-0.8": ("rendered", {"guided_match_threshold": 0.8}),
    "rendered gated-2sigma 2-rounds": ("rendered", {"guided_rounds": 2, "guided_gate_sigma": 2.0}),
    "rendered gated below-800": ("rendered", {"guided_below_inliers": 800}),
    "rendered no-checks": ("rendered", {"checks": "none"}),
    "rendered inlier-ratio-20%": ("rendered", {"checks": {"min_inlier_ratio": 0.2}}),
    "rendered no-confirmation": ("rendered", {"checks": {"confirm_below_inliers": 0}}),
    "rendered 2048-keypoints": ("rendered", {"max_keypoints": 2048}),
    "rendered 8192-keypoints": ("rendered", {"max_keypoints": 8192}),
    "rendered 2-iterations": ("rendered", {"iterations": 2}),
    # stop iterating once rendering again would change fewer than this share of the landmarks to match
    # (default 5 %; 0: every iteration runs)
    "rendered stop-0": ("rendered", {"stop_change": 0.0}),
    "rendered stop-1%": ("rendered", {"stop_change": 0.01}),
    "rendered stop-20%": ("rendered", {"stop_change": 0.2}),
    "rendered 2048-keypoints 2-iterations": ("rendered", {"max_keypoints": 2048, "iterations": 2}),
    # the Lowe ratio of the prior-free step (matching against all landmarks): run in every prior mode
    "rendered global-ratio-0.8": ("rendered", {"global_ratio": 0.8}),
    "rendered global-ratio-0.9": ("rendered", {"global_ratio": 0.9}),
    "rendered global-ratio-1.0": ("rendered", {"global_ratio": 1.0}),
    # the final pose refined with each landmark's position uncertainty (favormap.localize.refine; the
    # default: the keypoint noise of each landmark from its reprojection error), or not,
    # or for this keypoint noise (px) in the mapping images
    "rendered no-uncertainty": ("rendered", {"landmark_sigma_px": 0}),
    "rendered no-guided no-uncertainty": (
        "rendered",
        {"landmark_sigma_px": 0, "guided_radius_px": 0, "stop_change": 0.0},
    ),
    "mean no-guided": ("mean", {"guided_radius_px": 0}),
    "nearest-view no-guided": ("nearest", {"guided_radius_px": 0}),
    "rendered uncertainty-0.5px": ("rendered", {"landmark_sigma_px": 0.5}),
    "rendered uncertainty-1px": ("rendered", {"landmark_sigma_px": 1.0}),
    "rendered uncertainty-2px": ("rendered", {"landmark_sigma_px": 2.0}),
    "mean uncertainty-1px": ("mean", {"landmark_sigma_px": 1.0}),
    # ... with the keypoint noise estimated from the map's reprojection errors: one figure per map, or
    # per landmark
    "rendered uncertainty-map": ("rendered", {"landmark_sigma_px": "map"}),
    "rendered uncertainty-landmark": ("rendered", {"landmark_sigma_px": "landmark"}),
    "mean uncertainty-map": ("mean", {"landmark_sigma_px": "map"}),
    # the final refinement's noise model as the map says, not
    # fitted to each query's inliers (LocalizeConfig.refine_noise)
    "rendered noise-fixed": ("rendered", {"refine_noise": "fixed"}),
    "mean noise-fixed": ("mean", {"refine_noise": "fixed"}),
    "nearest-view noise-fixed": ("nearest", {"refine_noise": "fixed"}),
}
DEFAULT_VARIANTS = (
    "rendered",
    "mean",
    "nearest-view",
    "rendered align",
    "rendered no-guided",
    "mean no-guided",
    "nearest-view no-guided",
    "rendered gated every pose",
    "rendered noise-fixed",
    "mean noise-fixed",
    "rendered no-guided no-uncertainty",
    "rendered 8px no-mutual (old default)",
    "rendered no-checks",
)


# BuildConfig fields added with a default that changed the maps: their value in a stamp that lacks them
BEFORE_FIELD = {"min_frame_landmarks": 0}


def same_build(stamp: str, key: str) -> bool:
    """Whether a map built with ``stamp`` (an earlier build_or_load key: the config's JSON, then the
    mapping frames) is the map ``key`` asks for. A config field added since, at its default, does
    not make it another map where its default is the earlier behaviour; the fields whose default
    changed what a build does (BEFORE_FIELD) read as the value that meant the earlier behaviour."""
    from favormap.build import BuildConfig

    dec = json.JSONDecoder()
    try:
        old, end_old = dec.raw_decode(stamp)
        new, end_new = dec.raw_decode(key)
    except ValueError:
        return stamp == key

    def with_defaults(defaults, given):  # the stamp's config, with the fields it lacks at their default
        return {
            **defaults,
            **{k: with_defaults(defaults[k], v) if isinstance(defaults.get(k), dict) else v for k, v in given.items()},
        }

    defaults = json.loads(json.dumps(BuildConfig().to_dict(), sort_keys=True, default=str))
    defaults.update(BEFORE_FIELD)
    return stamp[end_old:] == key[end_new:] and with_defaults(defaults, old) == new


def build_key(build_cfg, mapping) -> str:
    """What identifies a map of the sequence ``mapping`` built with ``build_cfg`` (the stamp --reuse
    compares, :func:`same_build`): the config's JSON, then the frames and their cameras as read (a map
    built before a reader changed a camera, e.g. its focal length, is another map)."""
    cams = sorted(
        (int(i), c.model, int(c.width), int(c.height), [round(float(v), 6) for v in c.params], c.working_fov)
        for i, c in mapping.cameras.items()
    )
    return (
        json.dumps(build_cfg.to_dict(), sort_keys=True, default=str) + str([f.name for f in mapping.frames]) + str(cams)
    )


def build_or_load(split: Split, workdir: Path, build_cfg, reuse: bool, tag: str = "", device: str = "cpu"):
    from favormap.build import build_map
    from favormap.mapfile import write_map

    path = workdir / f"{split.files}{tag}.h5"
    key = build_key(build_cfg, split.mapping)
    stamp = path.with_suffix(".config")
    if reuse and path.exists() and stamp.exists() and same_build(stamp.read_text(), key):
        return path, None
    t = time.perf_counter()
    write_map(build_map(split.mapping, build_cfg, device=device), path)
    stamp.write_text(key)
    return path, time.perf_counter() - t


class ReuseLastExtraction:
    """Stands in for a localizer's extractor and remembers its last result, so that the diagnostics
    at the ground-truth pose reuse the features of the query just localized instead of extracting
    the same image again (a DISK extraction takes seconds on two cores). ``forget()`` before each
    timed query keeps the seconds per query honest: the timed call always extracts."""

    def __init__(self, extractor):
        self.extractor = extractor
        self.key, self.features = None, None

    def forget(self):
        self.key, self.features = None, None

    def extract(self, image):
        key = hashlib.sha1(np.ascontiguousarray(image).tobytes()).digest() + bytes(str(image.shape), "ascii")
        if key != self.key:
            self.key, self.features = key, self.extractor.extract(image)
        return self.features

    def __getattr__(self, name):
        return getattr(self.extractor, name)


def localizer_config(overrides: dict):
    from favormap.localize import LocalizeConfig, SuccessChecks

    over = dict(overrides)
    if isinstance(over.get("checks"), dict):
        over["checks"] = SuccessChecks(**over["checks"])
    if over.get("checks") == "none":
        over["checks"] = SuccessChecks(
            min_inliers=12,
            min_inlier_ratio=0.0,
            max_iteration_change=(np.inf, np.inf),
            min_visible_inliers=0.0,
            confirm_below_inliers=0,
        )
    return LocalizeConfig(**over)


def run_split(split: Split, args, build_cfgs) -> list[dict]:
    """Rows of one split: favormap maps of each build config (one per extractor), then the baseline."""
    rows, extent = [], None
    for name, cfg in build_cfgs:
        # a map of the build default keeps its old file name (so --reuse finds earlier maps)
        solver = cfg.voxel.solver
        tag = (
            ("" if cfg.extractor == args.default_extractor else f"-{cfg.extractor}")
            + ("" if solver == args.default_solver else f"-{solver}")
            + (f"-{name}" if name else "")
        )
        label = [cfg.extractor] * (len({c.extractor for _, c in build_cfgs}) > 1)
        label += [solver] * (len({c.voxel.solver for _, c in build_cfgs}) > 1)
        label += [name] * bool(name)
        prefix = "".join(f"{w} " for w in label)
        r, extent = run_favormap(split, args, cfg, tag, prefix, extent)
        rows += r
    if args.baseline:
        rows += run_baseline(split, args, build_cfgs[0][1], extent)
    return rows


def run_favormap(split: Split, args, build_cfg, tag: str, prefix: str, extent: float | None):
    """Rows of one favormap map, and the scene extent (the first map's landmarks, unless given:
    one extent per split, so that every method's false successes are judged alike)."""
    import dataclasses as dc

    from favormap.localize import Localizer, make_source
    from favormap.localize.descriptors import observation_descriptors
    from favormap.localize.evaluate import (
        EvalConfig,
        QueryOutcome,
        SequencePriors,
        localizer_noise_floor,
        make_priors,
        match_diagnostics,
        pose_nees,
        scene_extent,
    )
    from favormap.mapfile import Map

    workdir = Path(args.workdir)
    rows = []
    path, build_s = build_or_load(split, workdir, build_cfg, args.reuse, tag, args.device)
    m = Map.open(path)
    extent = extent or scene_extent(m.positions)
    print(
        f"[{split.name}] {build_cfg.extractor} ({build_cfg.voxel.solver}) map {len(m)} landmarks "
        f"from {len(split.mapping)} frames "
        f"({'reused' if build_s is None else f'built in {build_s:.0f} s'}), "
        f"{len(split.queries)} queries, scene extent {extent:.3f} units",
        file=sys.stderr,
    )
    obs_desc = None
    if any("nearest" in VARIANTS[v][0].split("+") for v in args.variants):
        obs_desc = observation_descriptors(m, split.mapping)

    for prior_mode in args.priors + [p for p in split.priors if p not in args.priors]:
        priors = make_priors(split.queries, m.rig_from_world, EvalConfig(prior_mode=prior_mode, seed=args.seed))
        # noise priors drawn with every --prior-seeds seed: each query's result is the seeds' median
        more = [
            make_priors(split.queries, m.rig_from_world, EvalConfig(prior_mode=prior_mode, seed=s))
            for s in (args.prior_seeds[1:] if prior_mode == "noise" else [])
        ]
        variants = (
            args.variants
            if prior_mode == "noise"
            else [v for v in args.variants if v == "rendered" or "global_ratio" in VARIANTS[v][1]]
        )
        for name in variants:
            source_name, over = VARIANTS[name]
            cfg = dc.replace(localizer_config(over), descriptors=source_name, device=args.device)
            loc = Localizer(m, cfg, descriptor_source=make_source(source_name, m, cfg.device, obs_desc))
            loc.extractor = ReuseLastExtraction(loc.extractor)
            outs = []
            seq_priors = SequencePriors(priors, prior_mode, loc)
            for i, fr in enumerate(split.queries.frames):
                cam = split.queries.cameras[fr.camera_id]
                prior = seq_priors.prior(i)
                loc.extractor.forget()
                t = time.perf_counter()
                res = loc.localize(fr.image_path, prior, cam)
                if more:
                    prior, res = median_over_priors(loc, fr, cam, [(prior, res)] + [(p[i], None) for p in more])
                seq_priors.update(res)
                # seconds per localization (a median over priors ran 1 + len(more) of them)
                o = QueryOutcome(fr.name, fr.cam_from_world, prior, res, (time.perf_counter() - t) / (1 + len(more)))
                if args.diagnostics:
                    o.diagnostics = match_diagnostics(loc, fr.image_path, cam, fr.cam_from_world)
                    o.diagnostics["nees"] = pose_nees(res, fr.cam_from_world)  # reported uncertainty against the error
                    o.diagnostics.update(localizer_noise_floor(loc, fr.image_path, cam, res))
                outs.append(o)
            seq_priors.close()
            rows.append(record(split, prefix + name, prior_mode, outs, cfg.iterations, extent, len(m)))
            rows[-1].update(
                per_query=[per_query(o, a) for o, a in zip(outs, _angles(split))],
                extractor=build_cfg.extractor,
                solver_tag=f" {build_cfg.voxel.solver}",
                map_variant=prefix.strip(),
                build_s=None if build_s is None else round(build_s, 1),
                map_bytes_per_landmark=path.stat().st_size / max(len(m), 1),
                build_stats={k: v for k, v in (m.provenance.get("stats") or {}).items() if np.isscalar(v)},
            )
    m.close()
    return rows, extent


def per_query(o, angle: float | None = None) -> dict:
    """One query's outcome for the JSON rows: error, success, inliers of the final and of the last
    descriptor-matched (rendering) iteration, the query's angle to the nearest mapping view, the
    camera centre's error vector (estimate - truth, world frame) and, where the localizer reported one,
    the camera centre's covariance and the NEES of the error under it."""
    from favormap.geometry import camera_centers, pose_error
    from favormap.localize.evaluate import pose_nees

    res = o.result
    est = getattr(res, "estimate", None)
    pose = res.cam_from_world if est is None else est
    dt, dr = pose_error(pose, o.gt)
    dc = camera_centers(np.stack([pose, o.gt]))
    iterations = getattr(res, "iterations", None) or []
    render = [it.num_inliers for it in iterations if it.kind == "render"]
    cov = getattr(res, "covariance", None) if res.success else None
    nees = pose_nees(res, o.gt) if cov is not None else None
    return dict(
        name=o.name,
        success=bool(res.success),
        t_err=round(float(dt), 6),
        r_err_deg=round(float(dr), 4),
        inliers=int(res.num_inliers),
        render_inliers=render[-1] if render else 0,
        iterations=[it.kind for it in iterations],
        **({} if angle is None else {"angle_deg": round(float(angle), 2)}),
        t_vec=[round(float(v), 6) for v in dc[0] - dc[1]],
        **({} if nees is None else {"nees": round(nees, 4)}),
        **({} if cov is None else {"center_cov": np.round(cov.center, 12).tolist()}),
    )


def run_baseline(split: Split, args, build_cfg, extent: float) -> list[dict]:
    """The baseline's rows: per query without a prior, and, with the 'stream' prior mode, the queries
    as a stream with the points refined from it (favormap.localize.baseline.PointRefinement)."""
    from favormap.io import load_image
    from favormap.localize.baseline import PointRefinement, StructureBaseline
    from favormap.localize.evaluate import QueryOutcome, diagnostics_from_matches, pose_noise_floor

    rows = []
    t = time.perf_counter()
    base = StructureBaseline.build(split.mapping, workdir=Path(args.workdir) / f"{split.files}_baseline")
    print(f"[{split.name}] baseline: {len(base.points3d)} points ({time.perf_counter() - t:.0f} s)", file=sys.stderr)
    runs = [("pycolmap-SIFT", "none", base)]
    if args.baseline_budget:
        runs.append((f"pycolmap-SIFT {args.baseline_budget} longest tracks", "none", base.subset(args.baseline_budget)))
    if "stream" in args.priors:
        runs.append(("pycolmap-SIFT", "stream", PointRefinement(base)))
    seeds = args.baseline_seeds
    for name, prior_mode, b in runs:
        outs = []
        for fr in split.queries.frames:
            cam = split.queries.cameras[fr.camera_id]
            pts = np.array(b.points3d, copy=True)  # a stream's: as refined up to this query
            if prior_mode == "none" and len(seeds) > 1:
                res = median_over_seeds(b, fr, cam, seeds)
            else:
                res = b.localize(fr.image_path, cam)
            o = QueryOutcome(fr.name, fr.cam_from_world, None, res, res.seconds)
            _, wcam = load_image(fr.image_path, cam, build_cfg.max_side)
            mm = np.asarray(res.matches, np.int64).reshape(-1, 2)
            o.diagnostics = diagnostics_from_matches(
                wcam, fr.cam_from_world, pts, res.keypoints, pts[mm[:, 0]], res.keypoints[mm[:, 1]]
            )
            if res.success and args.diagnostics:
                inl = mm[np.asarray(res.inlier_mask, bool)]
                o.diagnostics.update(
                    pose_noise_floor(wcam, res.cam_from_world, pts[inl[:, 0]], res.keypoints[inl[:, 1]])
                )
            outs.append(o)
        rows.append(record(split, name, prior_mode, outs, 1, extent, len(b.points3d)))
        rows[-1]["per_query"] = [per_query(o, a) for o, a in zip(outs, _angles(split))]
    return rows


def median_run(results: list, cam_from_world: np.ndarray) -> int:
    """Index of the run whose translation error against ``cam_from_world`` is the median of the runs'
    (failed runs count as infinite; the lower median of an even count), so that a query counts as
    localized when most runs localize it."""
    from favormap.geometry import pose_error

    err = [pose_error(r.cam_from_world, cam_from_world)[0] if r.success else np.inf for r in results]
    return int(np.argsort(err, kind="stable")[(len(err) - 1) // 2])


def median_over_priors(loc, fr, cam, tries: list) -> tuple:
    """favormap's result for one query over several noise priors, as :func:`median_over_seeds` takes the
    baseline's over RANSAC seeds: the (prior, result) of :func:`median_run`. ``tries``: (prior, result or
    None to localize from that prior)."""
    done = [(p, r if r is not None else loc.localize(fr.image_path, p, cam)) for p, r in tries]
    return done[median_run([r for _, r in done], fr.cam_from_world)]


def median_over_seeds(b, fr, cam, seeds):
    """The baseline's result for one query over several RANSAC seeds: the run of :func:`median_run`. The
    seconds are the mean over the runs."""
    import dataclasses as dc

    config = b.config
    results = []
    try:
        for seed in seeds:
            b.config = dc.replace(config, seed=int(seed))
            results.append(b.localize(fr.image_path, cam))
    finally:
        b.config = config
    pick = results[median_run(results, fr.cam_from_world)]
    return dc.replace(pick, seconds=float(np.mean([r.seconds for r in results])))


def _angles(split: Split) -> list:
    return [None] * len(split.queries) if split.angle is None else list(split.angle)


def record(
    split: Split, method: str, prior_mode: str, outcomes, iterations: int, extent: float, landmarks: int
) -> dict:
    from favormap.localize.evaluate import summarize

    s = summarize(outcomes, iterations, ((0.01, 1.0),), extent)
    s.update(split=split.name, method=method, prior=prior_mode, landmarks=landmarks)
    if split.angle is not None:
        err = np.array([_terr(o) for o in outcomes])
        succ = np.array([o.result.success for o in outcomes])
        s["bins"] = {}
        for lo, hi in ANGLE_BINS:
            sel = (split.angle >= lo) & (split.angle < hi)
            if sel.any():
                ok = sel & succ
                s["bins"][f"{lo}-{hi}"] = {
                    "queries": int(sel.sum()),
                    "localized": int(ok.sum()),
                    "median_translation": float(np.median(err[ok])) if ok.any() else None,
                    "precision": _mean([o.diagnostics.get("match_precision") for o, k in zip(outcomes, sel) if k]),
                }
    print(f"[{split.name}] {prior_mode:>8} | {method:<42} {fmt_row(s)}", file=sys.stderr)
    return s


def _terr(o) -> float:
    from favormap.geometry import pose_error

    return pose_error(o.result.cam_from_world, o.gt)[0]


def _mean(v):
    v = [x for x in v if x is not None]
    return float(np.mean(v)) if v else None
