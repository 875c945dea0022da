#!/usr/bin/env python3
"""Accuracy of favormap against the structure baseline: one process, the same queries, one table.

For every split a favormap map is built from the mapping frames and localized against with
  - rendered descriptors (FaVoR), the default localizer;
  - the same map with each landmark's mean observed descriptor;
  - the same map with the descriptor observed in the nearest mapping frame;
  - (``--variants``) other localizer settings, e.g. the pre-benchmark defaults;
and the pycolmap structure baseline (SIFT, triangulation from the known poses, one mean descriptor
per point, LO-RANSAC PnP; favormap.localize.baseline) is built from the same frames and localized
without a prior. Prior modes: noise (ground truth moved by 0.3 units / 10 deg), nearest mapping
frame, constant (first mapping frame), none, sequential (the queries as a stream: the first without
a prior, each next one from the poses estimated before it, constant velocity), stream (sequential,
and the landmarks refined from the queries localized so far: favormap.localize.stream).

Splits:
  fox-holdout  ../shared/data/fox, map from frames i % 5 != 0, queries 0, 5, 10, ...
  fox-extrap   the same sequence, map from the first half of the path, queries: every frame of the
               second half (--extrap-step 2: every 2nd, the earlier set)
  orbit        a synthetic room orbit with exact ground truth, map from part of the arc, queries beyond it
               and off it, binned by the angle to the nearest mapping view
  orbit-dense  the orbit's map, 53 queries at 4-degree steps beyond both ends of the arc and raised
               above it, 14 of them 10-20 deg from the nearest view (not in the default set)
  custom       --map SEQ --queries SEQ (any readable sequences)

Columns: median / 90th-percentile translation (scene units, and % of the scene extent: the 5-95 %
bounding-box diagonal of the landmarks), median rotation, localized %, false successes (reported
success with error > 5 % of the extent or > 5 deg), mean inliers, median translation after each
iteration, seconds per query, and at the ground-truth pose the match precision (share of matches
within 2 px of the landmark's projection) and the keypoint repeatability (share of visible
landmarks with a query keypoint within 2 px); last, the noise floor (median over the localized
queries of how far the pose moves when its own inlier correspondences are re-drawn with Gaussian
noise of their residual scale, from the median reprojection error, and refined again:
favormap.localize.evaluate.pose_noise_floor) and that residual. A median error near the floor
means the correspondences are right and only more inliers or smaller residuals can lower it; far
above it, wrong or biased correspondences. NEES: the camera-centre error normalised by the
covariance the localizer reports with the pose (median over the localized queries; 2.37, the median
of a chi-square with 3 degrees of freedom, when that covariance is right; larger: overconfident).

    python tools/bench_accuracy.py                       # fox-holdout, fox-extrap, orbit
    python tools/bench_accuracy.py --splits orbit --json out.json
    python tools/bench_accuracy.py --map SEQ --queries SEQ
    python tools/bench_accuracy.py --compare before.json after.json   # two runs, query by query
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import hashlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# ../shared/data beside the checkout (or beside the folder that holds it, for a git worktree)
DATA = Path(
    os.environ.get(
        "FAVORMAP_DATA",
        next((p / "shared" / "data" for p in ROOT.parents if (p / "shared" / "data").is_dir()), ROOT.parent / "shared"),
    )
)
FOX = Path(os.environ.get("FAVORMAP_FOX", DATA / "fox"))
ANGLE_BINS = ((0, 10), (10, 20), (20, 40), (40, 180))

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
    "rendered align 5-iterations stop-0.2deg": (
        "rendered",
        {"align": True, "iterations": 5, "stop_translation": 2e-3, "stop_rotation_deg": 0.2},
    ),
    "rendered 8px no-mutual (old default)": (
        "rendered",
        {"ransac_max_error_px": 8.0, "mutual": False, "ratio": 1.0, "landmark_sigma_px": 0, "guided_radius_px": 0},
    ),
    "rendered 2px": ("rendered", {"ransac_max_error_px": 2.0}),
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
    # stop iterating once an estimate lies this close to the pose its descriptors were rendered from
    # (default: 5e-3 x the median landmark distance and 0.5 deg)
    "rendered stop-0.01deg (before)": ("rendered", {"stop_translation": 1e-4, "stop_rotation_deg": 0.01}),
    "rendered stop-0.2deg": ("rendered", {"stop_translation": 2e-3, "stop_rotation_deg": 0.2}),
    "rendered stop-1deg": ("rendered", {"stop_translation": 1e-2, "stop_rotation_deg": 1.0}),
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
        {"landmark_sigma_px": 0, "guided_radius_px": 0, "stop_translation": 1e-4, "stop_rotation_deg": 0.01},
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


@dataclasses.dataclass
class Split:
    name: str
    mapping: object  # Sequence
    queries: object  # Sequence
    angle: np.ndarray | None = None  # per query: rotation to the nearest mapping view (deg)
    map_name: str | None = None  # the map (and baseline) files: another split's of the same mapping frames
    path_extent: float | None = None  # real sets: bounding-box diagonal of all the set's camera centres (units)
    units: str = "units"
    recall: tuple = ()  # real sets: (translation, rotation deg) recall thresholds in the set's units
    # a false success: localized with an error above (translation in the set's units, rotation deg); None:
    # 5 % of the path extent or 5 deg
    false_success: tuple | None = None
    priors: tuple = ()  # prior modes run on this split besides --priors
    cross: bool = False  # queries from another recording than the mapping frames

    @property
    def files(self) -> str:
        return self.map_name or self.name


def fox_splits(which: list[str], extrap_step: int = 1) -> list[Split]:
    from favormap.io import read_sequence

    if not FOX.exists():
        print(f"(skipping fox splits: {FOX} not found)", file=sys.stderr)
        return []
    seq = read_sequence(FOX)
    n = len(seq)
    out = []
    if "fox-holdout" in which:
        out.append(Split("fox-holdout", seq.subset([i for i in range(n) if i % 5]), seq.subset(list(range(0, n, 5)))))
    if "fox-extrap" in which:
        half = n // 2
        out.append(Split("fox-extrap", seq.subset(list(range(half))), seq.subset(list(range(half, n, extrap_step)))))
    for s in out:
        s.angle = nearest_view_angle(s.queries, s.mapping)
    return out


# the real sets, each read as shipped (favormap.io.read_sequence): folder, units, extra recall thresholds
REAL_SETS = {
    "fox": ("fox", "units", ()),
    "fern": ("llff_fern", "units", ()),
    "7scenes": ("7scenes_redkitchen_half", "m", ((0.05, 5.0), (0.02, 2.0))),
    "office": ("phone_office_colmap64", "units", ()),
    "cup": ("phone_cup_colmap77", "units", ()),
    "castle": ("strecha_castle_p30", "m", ()),
    "dino": ("middlebury_dino", "units", ()),
}
# the splits of each real set. holdout-K: every K-th frame held out as a query (in the reader's order),
# the map from the rest (queries between mapping views); sparse: the map from every 4th frame, queries
# midway (frames 2, 6, 10, ...); extrap: the map from the first half of the path, queries from the second
REAL_SPLITS = {
    "fox-holdout": ("fox", "holdout-5"),
    "fox-extrap": ("fox", "extrap"),
    "fern-holdout": ("fern", "holdout-3"),
    "7scenes-holdout": ("7scenes", "holdout-5"),
    "7scenes-sparse": ("7scenes", "sparse"),
    "office-holdout": ("office", "holdout-5"),
    "office-sparse": ("office", "sparse"),
    "cup-holdout": ("cup", "holdout-5"),
    "cup-sparse": ("cup", "sparse"),
    "castle-holdout": ("castle", "holdout-3"),
    "dino-holdout": ("dino", "holdout-5"),
}
# 7-Scenes with the focal its file holds (585 px, the depth camera's) instead of the reader's RGB focal
# (525 px; not in a suite: the focal measurement)
# 7-Scenes with the SfM pseudo ground truth of Brachmann et al. (ICCV 2021) for the same frames, the poses the
# FaVoR paper evaluates with, instead of the KinectFusion poses the set ships with (SEVENSCENES_PGT)
EXTRA_SPLITS = {
    "7scenes-holdout-f585": ("7scenes", "holdout-5"),
    "7scenes-sparse-f585": ("7scenes", "sparse"),
    "7scenes-holdout-pgt": ("7scenes", "holdout-5"),
    "7scenes-sparse-pgt": ("7scenes", "sparse"),
}
# queries from another recording of the same place, in the same world frame: name -> (map folder, query folder,
# units, recall thresholds, false success). The ground truth of TUM RGB-D disagrees with its images by ~1-2 cm
# and ~1 deg (SOURCE.md), so a false success is an error above 10 cm or 10 deg, well beyond that
CROSS_SPLITS = {
    "tum-desk-xyz": (
        "tum_fr1_desk_xyz/rgbd_dataset_freiburg1_desk",
        "tum_fr1_desk_xyz/rgbd_dataset_freiburg1_xyz",
        "m",
        ((0.02, 2.0), (0.05, 5.0), (0.10, 10.0)),
        (0.10, 10.0),
    ),
}
# the prior modes every cross-recording split runs: none, the nearest mapping frame (what image retrieval would
# give) and the noise prior
CROSS_PRIORS = ("noise", "nearest", "none")
SUITES = {
    "real": list(REAL_SPLITS) + list(CROSS_SPLITS),
    "cross": list(CROSS_SPLITS),
    "real-quick": ["7scenes-holdout", "cup-holdout", "castle-holdout", "dino-holdout", "fern-holdout"],
    "7scenes-pgt": ["7scenes-holdout", "7scenes-sparse", "7scenes-holdout-pgt", "7scenes-sparse-pgt"],
}
SEVENSCENES_PGT = ROOT / "tools" / "data" / "7scenes-redkitchen-sfm-pgt.txt"
# recall thresholds of every real set, as shares of its path extent (and degrees)
REAL_RECALL = ((0.005, 2.0), (0.02, 5.0))


def _natural_order(seq) -> list[int]:
    """Frame indices in the order of their names with numbers compared as numbers (IMG_2 before IMG_10):
    the capture order of a video whose reader lists the frames lexicographically."""
    import re

    def key(i):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", seq.frames[i].name)]

    return sorted(range(len(seq)), key=key)


def real_splits(which: list[str]) -> list[Split]:
    """The real-data splits in ``which`` (names of REAL_SPLITS / EXTRA_SPLITS), each set read as shipped."""
    from favormap.io import read_sequence
    from favormap.io.readers import sevenscenes_flat

    out, cache = [], {}
    for name in which:
        if name in CROSS_SPLITS:
            out += cross_split(name)
            continue
        spec = REAL_SPLITS.get(name) or EXTRA_SPLITS.get(name)
        if spec is None:
            continue
        key, kind = spec
        folder, units, extra_recall = REAL_SETS[key]
        root = DATA / folder
        if not root.exists():
            print(f"(skipping {name}: {root} not found)", file=sys.stderr)
            continue
        poses = name.rsplit("-", 1)[-1] if name.endswith(("-f585", "-pgt")) else "shipped"
        if (key, poses) not in cache:
            cache[key, poses] = (
                sevenscenes_flat.read_with_focal(root, "file")
                if poses == "f585"
                else with_pseudo_ground_truth(read_sequence(root), SEVENSCENES_PGT)
                if poses == "pgt"
                else read_sequence(root)
            )
        seq = cache[key, poses]
        n = len(seq)
        order = _natural_order(seq)
        if kind.startswith("holdout-"):
            k = int(kind.split("-")[1])
            m_idx, q_idx = [i for i in range(n) if i % k], list(range(0, n, k))
        elif kind == "sparse":
            m_idx, q_idx = [order[i] for i in range(0, n, 4)], [order[i] for i in range(2, n, 4)]
        else:  # extrap
            m_idx, q_idx = order[: n // 2], order[n // 2 :]
        centres = np.array([-f.cam_from_world[:3, :3].T @ f.cam_from_world[:3, 3] for f in seq.frames])
        ext = float(np.linalg.norm(centres.max(0) - centres.min(0)))
        recall = tuple((t * ext, r) for t, r in REAL_RECALL) + tuple(extra_recall)
        sp = Split(name, seq.subset(m_idx), seq.subset(q_idx), path_extent=ext, units=units, recall=recall)
        sp.angle = nearest_view_angle(sp.queries, sp.mapping)
        out.append(sp)
    return out


def cross_split(name: str) -> list[Split]:
    """The cross-recording split ``name`` (CROSS_SPLITS): the map from one recording as shipped, every frame of
    the other as a query; [] when the data is not there."""
    from favormap.io import read_sequence

    map_folder, query_folder, units, recall, false_success = CROSS_SPLITS[name]
    roots = [DATA / map_folder, DATA / query_folder]
    missing = [r for r in roots if not r.exists()]
    if missing:
        print(f"(skipping {name}: {missing[0]} not found)", file=sys.stderr)
        return []
    mapping, queries = (read_sequence(r) for r in roots)
    centres = np.array([-f.cam_from_world[:3, :3].T @ f.cam_from_world[:3, 3] for f in mapping.frames + queries.frames])
    ext = float(np.linalg.norm(centres.max(0) - centres.min(0)))
    sp = Split(name, mapping, queries, path_extent=ext, units=units, recall=recall, false_success=false_success)
    sp.priors, sp.cross = CROSS_PRIORS, True
    sp.angle = nearest_view_angle(queries, mapping)
    return [sp]


def with_pseudo_ground_truth(seq, path: Path):
    """``seq`` with the poses and focal of a pseudo ground truth file (one line per frame: image name,
    cam_from_world as quaternion w x y z and translation, focal in px), frames matched by their file stem.
    Refused when a frame has no pose there."""
    import dataclasses as dc

    from favormap.geometry import pose_from_quat_t

    def stem(name: str) -> str:
        return Path(name).name.split(".")[0]

    table = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, qw, qx, qy, qz, tx, ty, tz, focal = line.split()
            q, t = [float(qx), float(qy), float(qz), float(qw)], [float(tx), float(ty), float(tz)]
            table[stem(name)] = (pose_from_quat_t(q, t), float(focal))
    frames, focal = [], set()
    for fr in seq.frames:
        if stem(fr.name) not in table:
            raise SystemExit(f"{path}: no pose for frame {fr.name}")
        pose, f = table[stem(fr.name)]
        frames.append(dc.replace(fr, cam_from_world=pose))
        focal.add(f)
    if len(focal) != 1 or any(c.model != "PINHOLE" for c in seq.cameras.values()):
        raise SystemExit(f"{path}: expected one focal for pinhole cameras")
    f = focal.pop()
    cameras = {k: dc.replace(c, params=np.array([f, f, *c.params[2:]])) for k, c in seq.cameras.items()}
    return dc.replace(seq, cameras=cameras, frames=frames)


def nearest_view_angle(queries, mapping) -> np.ndarray:
    from favormap.geometry import pose_error

    return np.array(
        [min(pose_error(q.cam_from_world, m.cam_from_world)[1] for m in mapping.frames) for q in queries.frames]
    )


def orbit_split(workdir: Path, n_map: int, width: int, height: int, dense: bool = False) -> Split:
    """Mapping frames along part of the room orbit; queries (a) between mapping views, (b) orbiting
    on beyond the last mapping view, (c) raised above the path; binned by angle to the nearest view.

    ``dense`` ("orbit-dense", the same map): 53 queries instead of 25, at 4-degree steps orbiting
    7-59 degrees beyond both ends of the arc and raised 6-46 degrees above the path from four places
    along it (those whose camera leaves the room are dropped), 10 / 14 / 19 / 10 per angle bin. The
    standard set has 5 queries in the 10-20 degree bin, whose errors there lie at the pose's noise
    floor: a median over 5 of them moves more between two close methods than they differ."""
    from favormap.geometry import inverse, rotation_about
    from favormap.synthetic import camera_path, make_room, random_views_near, write_sequence

    scene = make_room(0)
    poses = camera_path(n_map)
    c = np.array([0.0, 0.55, 0.8])  # centre of the orbit (favormap.synthetic.paths._loop)

    def about(T, axis, deg):
        M = np.eye(4)
        M[:3, :3] = rotation_about(np.asarray(axis, float), np.radians(deg))
        M[:3, 3] = c - M[:3, :3] @ c
        return inverse(M @ inverse(T))

    q = list(random_views_near(poses, 4, seed=5, max_trans=0.03, max_rot_deg=3.0, scene=scene))
    last, first = poses[-1], poses[0]
    sign = 1.0 if np.cross(inverse(poses[-2])[:3, 3] - c, inverse(last)[:3, 3] - c)[2] > 0 else -1.0
    for deg in (6, 12, 18, 25, 32, 40, 45, 50, 55, 60, 70):
        q.append(about(last, [0, 0, 1], sign * deg))
    for base in (poses[len(poses) // 3], poses[2 * len(poses) // 3]):
        right = inverse(base)[:3, 0]  # camera x axis in world: tilting about it raises the camera over the scene
        for deg in (8, 15, 25, 35, 45):
            q.append(about(base, right, -deg))
    # before the first view too; the views beyond 40 deg (6 here) give that bin
    # of the angle table more than a couple of queries
    for deg in (10, 20, 45, 55):
        q.append(about(first, [0, 0, 1], -sign * deg))
    if dense:
        q = []
        for end, s in ((last, sign), (first, -sign)):
            q += [about(end, [0, 0, 1], s * deg) for deg in range(7, 61, 4)]
        for k in (1, 2, 3, 4):
            base = poses[k * len(poses) // 5]
            q += [about(base, inverse(base)[:3, 0], -deg) for deg in range(6, 47, 4)]
    q = [T for T in q if scene.camera_is_valid(inverse(T)[:3, 3])]
    mapping = write_sequence(workdir / "orbit_map", n_frames=n_map, width=width, height=height, scene=scene)
    name = "orbit-dense" if dense else "orbit"
    queries = write_sequence(
        workdir / f"{name.replace('-', '_')}_queries", poses=q, width=width, height=height, scene=scene
    )
    return Split(name, mapping, queries, nearest_view_angle(queries, mapping), map_name="orbit")


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
        priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode=prior_mode, seed=args.seed))
        # noise priors drawn with every --prior-seeds seed: each query's result is the seeds' median
        more = [
            make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode=prior_mode, seed=s))
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


PAIRED_BOOTSTRAP = 4000  # resamples of the queries for the paired ratio's confidence interval


def paired_ratio(errors: np.ndarray, reference: np.ndarray, seed: int = 0) -> dict | None:
    """How a method's per-query errors compare with a reference's on the same queries (both
    localized): the geometric mean of error / reference error with a 95 % bootstrap interval over the
    queries, and the queries where it is lower / higher. Medians of 5-25 queries move by 10 % between
    training seeds; a paired ratio whose interval excludes 1 is a difference the queries agree on."""
    e, r = np.asarray(errors, np.float64), np.asarray(reference, np.float64)
    ok = np.isfinite(e) & np.isfinite(r) & (e > 0) & (r > 0)
    if ok.sum() < 2:
        return None
    d = np.log(e[ok] / r[ok])
    rng = np.random.default_rng(seed)
    boot = d[rng.integers(0, len(d), (PAIRED_BOOTSTRAP, len(d)))].mean(axis=1)
    lo, hi = np.exp(np.percentile(boot, [2.5, 97.5]))
    return {
        "queries": int(ok.sum()),
        "ratio": float(np.exp(d.mean())),
        "ci95": [float(lo), float(hi)],
        "lower": int((d < 0).sum()),
        "higher": int((d > 0).sum()),
        "log_ratios": [round(float(v), 6) for v in d],  # per query, for intervals over several splits
    }


def _errors(row: dict, names: list[str]) -> np.ndarray:
    """A row's translation error per query ``names`` (inf where it failed or is missing)."""
    by = {q["name"]: (q["t_err"] if q["success"] else np.inf) for q in row.get("per_query", [])}
    return np.array([by.get(n, np.inf) for n in names], np.float64)


def _baseline_ref_prior(prior: str) -> str:
    """The prior mode of the favormap rows a baseline row is paired with: the noise priors for the
    baseline's own prior-free localization, the same mode for its stream."""
    return "noise" if prior == "none" else prior


def paired_rows(rows: list[dict], reference: str = "rendered") -> list[dict]:
    """Every method against ``reference`` on the same map, split and prior mode (and the baseline
    against the first map's reference under the noise priors), overall and per angle bin."""
    import re

    out = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r.get("per_query"):
            groups.setdefault((r["split"], r.get("map_variant")), []).append(r)
    for (split, variant), rs in groups.items():
        for prior in dict.fromkeys(r["prior"] for r in rs):
            ref = [
                r
                for r in rs
                if r["prior"] == prior and re.sub(rf"^{re.escape(variant or '')} ?", "", r["method"]) == reference
            ]
            if variant is None:  # the baseline: against the first map's reference (noise priors; a stream: a stream)
                ref = [r for r in rows if r["split"] == split and r.get("map_variant") is not None]
                ref = [r for r in ref if r["prior"] == _baseline_ref_prior(prior) and r["method"] == reference][:1]
            if not ref:
                continue
            names = [q["name"] for q in ref[0]["per_query"]]
            angle = np.array([q.get("angle_deg", np.nan) for q in ref[0]["per_query"]], np.float64)
            e_ref = _errors(ref[0], names)
            for r in rs:
                if r["prior"] != prior or r is ref[0]:
                    continue
                e = _errors(r, names)
                row = {"split": split, "prior": r["prior"], "method": r["method"], "reference": ref[0]["method"]}
                row["all"] = paired_ratio(e, e_ref)
                row["failed"] = int(np.isinf(e).sum()), int(np.isinf(e_ref).sum())
                if np.isfinite(angle).any():
                    row["bins"] = {
                        f"{lo}-{hi}": paired_ratio(e[(angle >= lo) & (angle < hi)], e_ref[(angle >= lo) & (angle < hi)])
                        for lo, hi in ANGLE_BINS
                    }
                out.append(row)
    return out


def _map_and_seed(r: dict, seed_of: dict | None = None) -> tuple[str | None, int, str]:
    """A row's map variant without its seed suffix (NAME-sK / sK -> NAME / ""), the seed, and the
    method without the map's prefix. ``seed_of``: {map name: training seed} of the run's builds; None:
    the seed read from the name as the benchmark writes it ("sK" / "NAME-sK" for seed K > 0)."""
    import re

    name = r.get("map_variant")
    if name is None:
        return None, 0, r["method"]
    method = re.sub(rf"^{re.escape(name)} ?", "", r["method"]) if name else r["method"]
    if seed_of is not None:
        base = re.sub(r"(^|-)s\d+$", "", name) if seed_of.get(name) else name
        return base, seed_of.get(name, 0), method
    m = re.fullmatch(r"(?:(.*)-)?s(\d+)", name)
    return (m.group(1) or "", int(m.group(2)), method) if m else (name, 0, method)


def seed_paired_rows(rows: list[dict], build_cfgs, reference: str = "rendered") -> list[dict]:
    """Every method of every map variant (and the baseline) against ``reference`` on the default map
    of the same training seed, query by query, with each query's log ratio averaged over the seeds
    before the bootstrap: one decision per (split, prior, map variant, method) over all seeds."""
    seed_of = {name: cfg.voxel.seed for name, cfg in build_cfgs}
    refs: dict[tuple, dict] = {}
    groups: dict[tuple, list[tuple[int, dict]]] = {}
    for r in rows:
        if not r.get("per_query"):
            continue
        base, seed, method = _map_and_seed(r, seed_of)
        if base == "" and method == reference:
            refs[(r["split"], r["prior"], seed)] = r
        groups.setdefault((r["split"], r["prior"], base, method), []).append((seed, r))
    out = []
    for (split, prior, base, method), members in groups.items():
        if base == "" and method == reference:
            continue
        logs, names, angle, seeds = [], None, None, set()
        for seed, r in members:
            if base is None:  # the baseline has no seed: against the default map of every seed
                against = [(k[2], v) for k, v in refs.items() if k[0] == split and k[1] == _baseline_ref_prior(prior)]
            else:
                against = [(seed, refs[split, prior, seed])] if (split, prior, seed) in refs else []
            for ref_seed, ref in against:
                if names is None:
                    names = [q["name"] for q in ref["per_query"]]
                    angle = np.array([q.get("angle_deg", np.nan) for q in ref["per_query"]], np.float64)
                with np.errstate(divide="ignore", invalid="ignore"):
                    logs.append(np.log(_errors(r, names) / _errors(ref, names)))
                seeds.add(ref_seed)
        if not logs:
            continue
        out.append(_seed_mean_row(split, prior, base, method, sorted(seeds), logs, angle))
    return out


def _seed_mean_row(split, prior, base, method, seeds, logs, angle) -> dict:
    """A paired row from per-seed log error ratios (seeds x queries): each query's mean over the
    seeds (nan / inf where a seed failed or tied at 0: left out), overall and per angle bin."""
    d = np.mean(logs, axis=0)
    row = {"split": split, "prior": prior, "map": base if base is not None else "(baseline)", "method": method}
    row["seeds"] = seeds
    row["all"] = paired_ratio(np.exp(d), np.ones_like(d))
    if np.isfinite(angle).any():
        row["bins"] = {
            f"{lo}-{hi}": paired_ratio(
                np.exp(d[(angle >= lo) & (angle < hi)]), np.ones(((angle >= lo) & (angle < hi)).sum())
            )
            for lo, hi in ANGLE_BINS
        }
    return row


def seed_paired_table(rows: list[dict], build_cfgs, reference: str = "rendered") -> str:
    """Markdown of :func:`seed_paired_rows`."""
    return _ratio_table(
        f"Paired with `{reference}` of the default map and the same training seed (per query, the log error ratio "
        "averaged over the seeds; geometric mean [95 % bootstrap interval over the queries], queries lower / higher):",
        ["split", "prior", "map", "method", "seeds"],
        [
            ([p["split"], p["prior"], p["map"] or "(default)", p["method"], ",".join(map(str, p["seeds"]))], p)
            for p in seed_paired_rows(rows, build_cfgs, reference)
        ],
    )


def paired_table(rows: list[dict], reference: str = "rendered") -> str:
    """Markdown of :func:`paired_rows`: ratio [95 % interval] and queries lower/higher."""
    return _ratio_table(
        f"Paired with `{reference}` of the same map (error / reference error, geometric mean over the queries both "
        "localized [95 % bootstrap interval], queries lower / higher; < 1: better than the reference):",
        ["split", "prior", "method", "failed (method / ref.)"],
        [
            ([p["split"], p["prior"], p["method"], f"{p['failed'][0]} / {p['failed'][1]}"], p)
            for p in paired_rows(rows, reference)
        ],
    )


def read_rows(path) -> list[dict]:
    """A run's --json rows, from a plain or a gzip-compressed (``.gz``) file."""
    path = Path(path)
    raw = path.read_bytes()
    return json.loads(gzip.decompress(raw) if path.suffix == ".gz" else raw)


def write_rows(path, rows: list[dict]) -> None:
    """Write a run's rows as JSON; gzip-compressed where the name ends in ``.gz`` (docs/benchmarks keeps
    its runs so: they are ~14x smaller, and the working tree a GPU check carries is limited to 64 MiB)."""
    path = Path(path)
    text = json.dumps(rows, indent=1, default=float).encode()
    path.write_bytes(gzip.compress(text, mtime=0) if path.suffix == ".gz" else text)


def compare_rows(ref_rows: list[dict], new_rows: list[dict]) -> list[dict]:
    """Two runs of the benchmark (e.g. two versions of the code, the same splits and seeds): every
    (split, prior, map, method) in both, the new run's error over the reference run's query by query
    and seed by seed, each query's log ratio averaged over the seeds both runs have."""
    ref = {}
    for r in ref_rows:
        if r.get("per_query"):
            base, seed, method = _map_and_seed(r)
            ref[(r["split"], r["prior"], base, method, seed)] = r
    groups: dict[tuple, list[tuple[int, dict]]] = {}
    for r in new_rows:
        if r.get("per_query"):
            base, seed, method = _map_and_seed(r)
            if (r["split"], r["prior"], base, method, seed) in ref:
                groups.setdefault((r["split"], r["prior"], base, method), []).append((seed, r))
    out = []
    for (split, prior, base, method), members in groups.items():
        logs, names, angle = [], None, None
        for seed, r in sorted(members, key=lambda m: m[0]):
            old = ref[(split, prior, base, method, seed)]
            if names is None:
                names = [q["name"] for q in old["per_query"]]
                angle = np.array([q.get("angle_deg", np.nan) for q in old["per_query"]], np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                logs.append(np.log(_errors(r, names) / _errors(old, names)))
        out.append(_seed_mean_row(split, prior, base, method, sorted(m[0] for m in members), logs, angle))
    return out


def compare_table(ref_rows: list[dict], new_rows: list[dict]) -> str:
    """Markdown of :func:`compare_rows`."""
    return _ratio_table(
        "New run / reference run, the same method on the same queries (per query, the log error ratio averaged "
        "over the seeds; geometric mean [95 % bootstrap interval over the queries], queries lower / higher; "
        "< 1: the new run is better):",
        ["split", "prior", "map", "method", "seeds"],
        [
            ([p["split"], p["prior"], p["map"] or "(default)", p["method"], ",".join(map(str, p["seeds"]))], p)
            for p in compare_rows(ref_rows, new_rows)
        ],
    )


def _ratio_cell(p: dict | None) -> str:
    if p is None:
        return "-"
    return f"{p['ratio']:.2f} [{p['ci95'][0]:.2f}, {p['ci95'][1]:.2f}] {p['lower']}/{p['higher']}"


def _ratio_table(intro: str, lead: list[str], entries: list[tuple[list[str], dict]]) -> str:
    """A markdown table of paired ratios: the ``lead`` columns, then all queries and each angle bin."""
    if not entries:
        return ""
    bins = [f"{lo}-{hi}" for lo, hi in ANGLE_BINS]
    out = [
        intro,
        "",
        "| " + " | ".join(lead + ["all queries"] + bins) + " |",
        "|---" * (len(lead) + 1 + len(bins)) + "|",
    ]
    for cells, p in entries:
        b = p.get("bins") or {}
        out.append(
            "| "
            + " | ".join(cells + [_ratio_cell(p["all"])] + [_ratio_cell(b.get(k)) if b else "" for k in bins])
            + " |"
        )
    return "\n".join(out)


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


def _query_arrays(row: dict, names: list[str]):
    by = {q["name"]: q for q in row["per_query"]}
    qs = [by.get(n) for n in names]
    succ = np.array([bool(q and q["success"]) for q in qs])
    t = np.array([q["t_err"] if q else np.inf for q in qs], np.float64)
    r = np.array([q["r_err_deg"] if q else np.inf for q in qs], np.float64)
    return succ, t, r


def _method_stats(split: Split, row: dict, names: list[str]) -> dict:
    """One method's figures on a real split, from its per-query rows: medians over the localized
    queries in the set's units and as % of the path extent, recall, localized share, false successes
    (localized with an error above the split's false_success: 5 % of the path extent or 5 deg unless it
    says otherwise) and the median NEES of the reported covariance."""
    succ, t, r = _query_arrays(row, names)
    ext = split.path_extent
    fs_t, fs_r = split.false_success or (0.05 * ext, 5.0)
    med_t = float(np.median(t[succ])) if succ.any() else None
    by = {q["name"]: q for q in row["per_query"]}
    nees = [by[n]["nees"] for n in names if n in by and by[n].get("nees") is not None]
    return {
        "median_t": med_t,
        "median_t_pct_path": None if med_t is None else 100 * med_t / ext,
        "median_r_deg": float(np.median(r[succ])) if succ.any() else None,
        "recall": {f"{tt:.4g}/{rr:g}deg": float(np.mean(succ & (t <= tt) & (r <= rr))) for tt, rr in split.recall},
        "localized": int(succ.sum()),
        "queries": len(names),
        "false_successes": int((succ & ((t > fs_t) | (r > fs_r))).sum()),
        "median_nees": float(np.median(nees)) if nees else None,
    }


def real_rows(rows: list[dict], splits: list[Split], reference: str = "rendered") -> list[dict]:
    """Per real split and favormap map (the default and each --build-variant): favormap's ``reference``
    method under the noise priors and the baseline side by side, with the paired ratio of their
    translation errors (favormap / baseline over the queries both localized, 95 % bootstrap interval)."""
    out = []
    for sp in splits:
        if sp.path_extent is None:
            continue
        base = [r for r in rows if r["split"] == sp.name and r["method"] == "pycolmap-SIFT" and r["prior"] == "none"]
        favs = [
            r
            for r in rows
            if r["split"] == sp.name
            and (r["prior"] in CROSS_PRIORS if sp.cross else r["prior"] == "noise")
            and r.get("map_variant") is not None
            and r["method"] == " ".join(w for w in (r["map_variant"], reference) if w)
        ]
        names = [f.name for f in sp.queries.frames]
        b_stats = _method_stats(sp, base[0], names) if base else None
        for f in favs:
            entry = {
                "split": sp.name,
                "prior": f["prior"],
                "cross": sp.cross,
                "map": f["map_variant"] or "(default)",
                "mapping_frames": len(sp.mapping),
                "units": sp.units,
                "path_extent": sp.path_extent,
                "favormap": _method_stats(sp, f, names),
                "landmarks": f.get("landmarks"),
                "build_s_per_frame": None if f.get("build_s") is None else f["build_s"] / len(sp.mapping),
                "map_bytes_per_landmark": f.get("map_bytes_per_landmark"),
                "build_stats": f.get("build_stats"),
            }
            if base:
                succ_f, t_f, _ = _query_arrays(f, names)
                succ_b, t_b, _ = _query_arrays(base[0], names)
                entry["baseline"] = b_stats
                entry["baseline_points"] = base[0].get("landmarks")
                entry["ratio"] = paired_ratio(np.where(succ_f, t_f, np.inf), np.where(succ_b, t_b, np.inf))
                entry["baseline_only"] = int((succ_b & ~succ_f).sum())  # localized by the baseline, not by favormap
                entry["shared"] = shared_error(f, base[0], names)
                if sp.cross and entry["shared"]:
                    entry["favormap"]["median_nees_gt"] = nees_with_ground_truth_error(
                        f, names, entry["shared"]["gt_sigma"]
                    )
            out.append(entry)
    return out


def shared_error(row: dict, base: dict, names: list[str]) -> dict | None:
    """How much of two methods' errors they share, over the queries both localized: the median distance
    between their camera centres, and the median cosine between their centres' error vectors. Errors
    that point the same way and estimates that lie closer to each other than to the truth are the
    ground truth's (or the given mapping poses') own error, which neither method can remove."""
    a = {q["name"]: q for q in row.get("per_query", []) if q["success"] and "t_vec" in q}
    b = {q["name"]: q for q in base.get("per_query", []) if q["success"] and "t_vec" in q}
    both = [n for n in names if n in a and n in b]
    if len(both) < 2:
        return None
    ea = np.array([a[n]["t_vec"] for n in both])
    eb = np.array([b[n]["t_vec"] for n in both])
    norm = np.linalg.norm(ea, axis=1) * np.linalg.norm(eb, axis=1)
    cos = np.sum(ea * eb, 1) / np.maximum(norm, 1e-300)
    return {
        "queries": len(both),
        "apart": float(np.median(np.linalg.norm(ea - eb, axis=1))),
        "cosine": float(np.median(cos)),
        # the ground truth's own error per axis: two methods' errors e_a = g + a and e_b = g + b share the ground
        # truth's g, and with a, b independent of g and of each other E[e_a . e_b] = E|g|^2 = 3 sigma^2
        "gt_sigma": float(np.sqrt(max(np.mean(np.sum(ea * eb, 1)), 0.0) / 3)),
    }


def nees_with_ground_truth_error(row: dict, names: list[str], gt_sigma: float) -> float | None:
    """Median NEES of a method's localized queries against a ground truth with ``gt_sigma`` of its own error
    per axis: the camera-centre error under the reported covariance plus gt_sigma^2 I (chi-square with 3
    degrees of freedom, median 2.37, when both are right)."""
    by = {q["name"]: q for q in row.get("per_query", [])}
    out = []
    for n in names:
        q = by.get(n)
        if q and q["success"] and "center_cov" in q:
            e = np.asarray(q["t_vec"], np.float64)
            C = np.asarray(q["center_cov"], np.float64) + gt_sigma**2 * np.eye(3)
            try:
                out.append(float(e @ np.linalg.solve(C, e)))
            except np.linalg.LinAlgError:
                continue
    return float(np.median(out)) if out else None


def geometric_means(entries: list[dict], seed: int = 0) -> dict[str, tuple[float, list[float] | None]]:
    """Per favormap map: the geometric mean over the same-recording splits of the paired ratios to the
    baseline, and its 95 % bootstrap interval (each split's queries resampled within the split; None where a
    ratio lacks its per-query log ratios). Cross-recording splits are reported on their own."""
    by: dict[str, list[dict]] = {}
    for e in entries:
        if e.get("ratio") and not e.get("cross"):
            by.setdefault(e["map"], []).append(e["ratio"])
    rng = np.random.default_rng(seed)
    out = {}
    for k, ratios in by.items():
        value = float(np.exp(np.mean([np.log(r["ratio"]) for r in ratios])))
        ci = None
        if all(r.get("log_ratios") for r in ratios):
            boot = np.mean(
                [
                    np.asarray(r["log_ratios"])[
                        rng.integers(0, len(r["log_ratios"]), (PAIRED_BOOTSTRAP, len(r["log_ratios"])))
                    ].mean(1)
                    for r in ratios
                ],
                axis=0,
            )
            ci = [float(v) for v in np.exp(np.percentile(boot, [2.5, 97.5]))]
        out[k] = (value, ci)
    return out


def _split_label(entry: dict) -> str:
    """A real-table entry's split, with its prior mode where a cross-recording split runs several."""
    return entry["split"] + (f" ({entry['prior']} prior)" if entry.get("cross") else "")


def real_table(entries: list[dict]) -> str:
    """Markdown of :func:`real_rows`, and one line per favormap map: the geometric mean of the ratios."""
    if not entries:
        return ""
    rec_keys = []
    for e in entries:
        for k in range(len(e["favormap"]["recall"])):
            rec_keys.append(k) if k not in rec_keys else None

    def st(s, e):
        if s is None:
            return ["-"] * 5
        rec = " / ".join(f"{100 * v:.0f}" for v in s["recall"].values())
        return [
            f"{_f(s['median_t'], '.4f')} ({_f(s['median_t_pct_path'], '.2f')} %)",
            _f(s["median_r_deg"], ".3f"),
            rec,
            f"{s['localized']}/{s['queries']}",
            str(s["false_successes"]),
        ]

    out = [
        "| split | map | frames map / queries | path extent | favormap median t (% path) | R (deg) | recall % | "
        "localized | FS | NEES | baseline median t (% path) | R (deg) | recall % | localized | FS | favormap / "
        "baseline [95 % CI] | baseline-only | landmarks / points | build s/frame | map B/landmark |",
        "|---" * 20 + "|",
    ]
    for e in entries:
        r = e.get("ratio")
        ratio = "-" if not r else f"{r['ratio']:.2f} [{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}]"
        bps = e.get("build_s_per_frame")
        bpl = e.get("map_bytes_per_landmark")
        out.append(
            "| "
            + " | ".join(
                [
                    _split_label(e),
                    e["map"],
                    f"{e['mapping_frames']} / {e['favormap']['queries']}",
                    f"{e['path_extent']:.3f} {e['units']}",
                    *st(e["favormap"], e),
                    _f(e["favormap"].get("median_nees"), ".1f"),
                    *st(e.get("baseline"), e),
                    ratio,
                    str(e.get("baseline_only", "-")),
                    f"{e.get('landmarks') or '-'} / {e.get('baseline_points') or '-'}",
                    _f(bps, ".2f"),
                    _f(bpl, ".0f"),
                ]
            )
            + " |"
        )
    out.append("")
    out.append(
        "Recall thresholds: 0.5 % of the path extent / 2 deg, 2 % / 5 deg (and for 7-Scenes 5 cm / 5 deg, "
        "2 cm / 2 deg); FS: false successes (localized, error > 5 % of the path extent or 5 deg). Another "
        "recording (tum-desk-xyz): recall at 2 cm / 2 deg, 5 cm / 5 deg, 10 cm / 10 deg, a false success beyond "
        "10 cm or 10 deg (its ground truth is off by ~1-2 cm itself), favormap from each prior mode, the baseline "
        "without a prior. NEES: median over the localized queries of the camera-centre error under the reported "
        "covariance (2.37 when that covariance is right)."
    )
    for k, (v, ci) in geometric_means(entries).items():
        n = sum(1 for e in entries if e["map"] == k and e.get("ratio") and not e.get("cross"))
        interval = "" if ci is None else f" [{ci[0]:.3f}, {ci[1]:.3f}]"
        out.append(f"geometric mean of favormap / baseline over {n} splits, map {k}: {v:.3f}{interval}")
    shared = [e for e in entries if e.get("shared")]
    if shared:
        out += [
            "",
            "Error shared with the baseline (queries both localize): the median distance between the two "
            "estimates, against each method's median error, the median cosine between their error vectors, the "
            "ground truth's own error per axis that the two share (sqrt of the mean dot product of their error "
            "vectors over 3) and, on another recording, favormap's median NEES with that error added to its "
            "covariance",
            "",
            "| split | map | estimates apart | favormap median t | baseline median t | cosine of the errors | "
            "ground truth's error per axis | favormap NEES with it |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for e in shared:
            sh = e["shared"]
            out.append(
                f"| {_split_label(e)} | {e['map']} | {sh['apart']:.4f} | {_f(e['favormap']['median_t'], '.4f')} | "
                f"{_f(e['baseline']['median_t'], '.4f')} | {sh['cosine']:.2f} | {sh['gt_sigma']:.4f} | "
                f"{_f(e['favormap'].get('median_nees_gt'), '.1f')} |"
            )
    return "\n".join(out)


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


def _f(v, spec):
    return "-" if v is None else format(v, spec)


def fmt_row(s: dict) -> str:
    iters = "/".join(_f(it["median_translation"], ".4f") for it in s["per_iteration"])
    return (
        f"med {_f(s['median_translation'], '.4f')} ({_f(s['median_translation_pct_extent'], '.2f')} %) "
        f"p90 {_f(s['p90_translation'], '.4f')}  R {_f(s['median_rotation_deg'], '.3f')}  "
        f"loc {100 * s['success_rate']:.0f} %  FS {s['false_successes']}  inl {s['mean_inliers']:.0f}  "
        f"iters {iters}  {s['mean_time_s'] * 1000:.0f} ms  prec {_f(s['match_precision'], '.2f')}  "
        f"rep {_f(s['keypoint_repeatability'], '.2f')}  floor {_f(s.get('median_noise_floor'), '.4f')}  "
        f"NEES {_f(s.get('median_nees'), '.1f')}"
    )


def seed_table(rows: list[dict], build_cfgs) -> str:
    """Markdown table of each favormap method's median translation across the training seeds of
    its map (rows of maps named NAME-sK / sK are grouped with NAME's)."""
    import re

    seed_of = {name: cfg.voxel.seed for name, cfg in build_cfgs}
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if "map_variant" not in r:  # the baseline
            continue
        name = r["map_variant"]
        base = re.sub(r"(^|-)s\d+$", "", name) if seed_of.get(name) else name
        method = r["method"] if name == base else re.sub(rf"(^| ){re.escape(name)}( |$)", rf"\1{base}\2", r["method"])
        key = (r["split"], r["prior"], " ".join(method.split()))
        groups.setdefault(key, []).append(dict(r, seed=seed_of.get(name, 0)))
    out = [
        "| split | prior | method | seeds | median t per seed (units) | range | mean | localized | false succ. |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (split, prior, method), rs in groups.items():
        rs.sort(key=lambda r: r["seed"])
        med = [r["median_translation"] for r in rs]
        ok = [m for m in med if m is not None]
        fmt = [f"{m:.4f}" if m is not None else "-" for m in med]
        rng = f"{min(ok):.4f}-{max(ok):.4f}" if ok else "-"
        mean = f"{np.mean(ok):.4f}" if ok else "-"
        loc = f"{sum(r['localized'] for r in rs)}/{sum(r['queries'] for r in rs)}"
        fs = sum(r["false_successes"] for r in rs)
        seeds = ",".join(str(r["seed"]) for r in rs)
        out.append(f"| {split} | {prior} | {method} | {seeds} | {' / '.join(fmt)} | {rng} | {mean} | {loc} | {fs} |")
    return "\n".join(out)


def markdown(rows: list[dict]) -> str:
    out = [
        "| split | prior | method | landmarks | median t (units) | % extent | p90 t | median R (deg) | localized | "
        "false succ. | inliers | median t per iter | s/query | match prec. @GT | kp repeat. @GT | noise floor | "
        "residual px | median NEES |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in rows:
        iters = " / ".join(_f(it["median_translation"], ".4f") for it in s["per_iteration"])
        out.append(
            f"| {s['split']} | {s['prior']} | {s['method']} | {s.get('landmarks') or '-'} | "
            f"{_f(s['median_translation'], '.4f')} | {_f(s['median_translation_pct_extent'], '.2f')} | "
            f"{_f(s['p90_translation'], '.4f')} | {_f(s['median_rotation_deg'], '.3f')} | "
            f"{s['localized']}/{s['queries']} | {s['false_successes']} | {s['mean_inliers']:.0f} | {iters} | "
            f"{s['mean_time_s']:.2f} | {_f(s['match_precision'], '.2f')} | {_f(s['keypoint_repeatability'], '.2f')} | "
            f"{_f(s.get('median_noise_floor'), '.4f')} | {_f(s.get('median_residual_px'), '.2f')} | "
            f"{_f(s.get('median_nees'), '.1f')} |"
        )
    bins = [s for s in rows if s.get("bins")]
    if bins:
        out += [
            "",
            "Per angle to the nearest mapping view (deg): localized / queries, median translation (units), match "
            "precision @GT",
            "",
            "| split | prior | method | " + " | ".join(f"{lo}-{hi}" for lo, hi in ANGLE_BINS) + " |",
            "|---|---|---|" + "---|" * len(ANGLE_BINS),
        ]
        for s in bins:
            cells = []
            for lo, hi in ANGLE_BINS:
                b = s["bins"].get(f"{lo}-{hi}")
                cells.append(
                    "-"
                    if b is None
                    else f"{b['localized']}/{b['queries']}, {_f(b['median_translation'], '.4f')}, "
                    f"{_f(b['precision'], '.2f')}"
                )
            out.append(f"| {s['split']} | {s['prior']} | {s['method']} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default="fox-holdout,fox-extrap,orbit")
    ap.add_argument(
        "--suite",
        choices=sorted(SUITES),
        help="the real-data suite (every set of ../shared/data read as shipped, the baseline side by side; "
        "real-quick: a subset; 7scenes-pgt: 7-Scenes with its shipped poses and with the SfM pseudo ground "
        "truth of the same frames): sets --splits, --priors noise, --variants rendered, --baseline-seeds 0,1,2 "
        "and --prior-seeds 0,1,2 unless given, and no per-query diagnostics",
    )
    ap.add_argument(
        "--baseline-seeds",
        default=None,
        help="the baseline's RANSAC seeds (comma-separated): each query's result is the seeds' median "
        "(default 0; the suite: 0,1,2)",
    )
    ap.add_argument(
        "--no-diagnostics",
        dest="diagnostics",
        action="store_false",
        help="skip the per-query diagnostics at the ground-truth pose (match precision, noise floor, NEES)",
    )
    ap.add_argument("--map", help="custom split: mapping sequence")
    ap.add_argument("--queries", help="custom split: query sequence")
    ap.add_argument("--priors", default="noise,nearest,constant,none,sequential,stream")
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=", ".join(VARIANTS).replace("%", "%%"))
    ap.add_argument(
        "--extractor",
        default=None,
        help="build with this extractor, or several (comma-separated: one map each, one table; "
        "default: the build default)",
    )
    ap.add_argument(
        "--solver",
        default=None,
        help="voxel training solver, or several (comma-separated: one map each; adam | lstsq; default: the build "
        "default, adam)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="VoxelConfig or BuildConfig override for every map built (repeatable; e.g. --set init=lstsq "
        "--set iterations=60)",
    )
    ap.add_argument(
        "--build-variant",
        action="append",
        default=[],
        metavar="NAME:KEY=VALUE,...",
        help="also build a map with these VoxelConfig or BuildConfig overrides (repeatable; one map each, its rows "
        "prefixed with NAME; e.g. --build-variant cf-dens20:solver=lstsq,density_init=20 or w6:match_window=6)",
    )
    ap.add_argument("--min-track", type=int, default=None)
    ap.add_argument("--max-landmarks", type=int, default=None)
    ap.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="Adam iterations (--quality fast / reference; the closed-form presets have none)",
    )
    ap.add_argument(
        "--quality",
        default=None,
        help="voxel training preset (quick | balanced | fast | reference; default: the build default)",
    )
    ap.add_argument("--device", default="cpu", help="torch device for training and localization (cpu | cuda)")
    ap.add_argument("--orbit-frames", type=int, default=24)
    ap.add_argument(
        "--extrap-step",
        type=int,
        default=1,
        help="fox-extrap queries: every STEP-th frame of the second half (default 1: 20 queries)",
    )
    ap.add_argument("--no-baseline", dest="baseline", action="store_false")
    ap.add_argument(
        "--baseline-budget", type=int, default=0, help="also run the baseline restricted to N longest tracks"
    )
    ap.add_argument("--workdir", default="/tmp/favormap-bench-accuracy")
    ap.add_argument("--reuse", action="store_true", help="reuse maps in --workdir built with the same settings")
    ap.add_argument("--seed", type=int, default=0, help="seed of the query priors")
    ap.add_argument(
        "--prior-seeds",
        default=None,
        help="seeds of the noise priors (comma-separated): each query's favormap result is the median over "
        "its priors, as the baseline's is over --baseline-seeds (default: --seed alone)",
    )
    ap.add_argument(
        "--train-seeds",
        help="build every map once per voxel-training seed (e.g. 0,1,2; a seed K > 0 adds -sK to the map's "
        "name) and add a table of each method's median across the seeds: a rebuild with another seed moves "
        "the fox extrapolation median by ~11 %%, so compare variants over seeds",
    )
    ap.add_argument("--json", help="write all rows to this JSON file (gzip-compressed where it ends in .gz)")
    ap.add_argument(
        "--compare",
        nargs=2,
        metavar=("REF.json", "NEW.json"),
        help="run nothing: compare two runs' --json rows (plain or .gz) query by query (e.g. two versions of the code)",
    )
    args = ap.parse_args()
    if args.compare:
        try:
            ref_rows, new_rows = (read_rows(f) for f in args.compare)
        except (OSError, ValueError) as e:
            ap.error(f"--compare: {e}")
        table = compare_table(ref_rows, new_rows)
        print(table or "--compare: no (split, prior, map, method, seed) in both runs")
        return 0 if table else 1
    if args.suite:
        args.splits = ",".join(SUITES[args.suite])
        given = set(sys.argv)
        if "--priors" not in given:
            args.priors = "noise"
        if "--variants" not in given:
            args.variants = "rendered"
        args.diagnostics = False
        args.baseline_seeds = args.baseline_seeds or "0,1,2"
        args.prior_seeds = args.prior_seeds or "0,1,2"
    try:
        args.baseline_seeds = [int(x) for x in (args.baseline_seeds or "0").split(",") if x.strip()]
    except ValueError:
        ap.error(f"--baseline-seeds {args.baseline_seeds!r}: expected integers, e.g. 0,1,2")
    try:
        args.prior_seeds = [int(x) for x in (args.prior_seeds or str(args.seed)).split(",") if x.strip()]
    except ValueError:
        ap.error(f"--prior-seeds {args.prior_seeds!r}: expected integers, e.g. 0,1,2")
    if not args.prior_seeds:
        ap.error("--prior-seeds: no seed given")
    args.seed = args.prior_seeds[0]
    args.priors = [p for p in args.priors.split(",") if p]
    args.variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; known: {list(VARIANTS)}")

    from favormap import features
    from favormap.build import BuildConfig

    args.default_extractor = BuildConfig().extractor
    args.default_solver = BuildConfig().voxel.solver
    extractors = [e.strip() for e in (args.extractor or args.default_extractor).split(",") if e.strip()]
    bad = [e for e in extractors if e not in features.available()]
    if bad or not extractors:
        ap.error(f"unknown extractor(s) {bad}; known: {features.available()}")
    solvers = [s.strip() for s in (args.solver or "").split(",") if s.strip()] or [None]
    variants = [("", [])]
    for spec in args.build_variant:
        name, _, kvs = spec.partition(":")
        if not name or not kvs or not name.replace("-", "").replace(".", "").isalnum():
            ap.error(f"--build-variant {spec!r}: expected NAME:KEY=VALUE,... (NAME of letters, digits, - and .)")
        variants.append((name, [kv.strip() for kv in kvs.split(",") if kv.strip()]))
    train_seeds = [None]
    if args.train_seeds:
        try:
            train_seeds = sorted({int(x) for x in args.train_seeds.split(",") if x.strip()})
        except ValueError:
            ap.error(f"--train-seeds {args.train_seeds!r}: expected integers, e.g. 0,1,2")
        if any(kv.startswith("seed=") for kv in args.set + [kv for _, vs in variants for kv in vs]):
            ap.error("--train-seeds sets VoxelConfig.seed: leave seed= out of --set and --build-variant")
    build_cfgs = []
    for ex, solver, (vname, vset), seed in [
        (e, s, v, k) for e in extractors for s in solvers for v in variants for k in train_seeds
    ]:
        if seed:
            vset = vset + [f"seed={seed}"]
            vname = f"{vname}-s{seed}" if vname else f"s{seed}"
        build_cfg = BuildConfig(extractor=ex)
        if args.quality:
            from favormap.voxels import VoxelConfig

            build_cfg.voxel = VoxelConfig.preset(args.quality)
        if solver:
            build_cfg.voxel.solver = solver
        for kv in args.set + vset:
            k, _, v = kv.partition("=")
            target = build_cfg.voxel if hasattr(build_cfg.voxel, k) else build_cfg
            if not v or k == "voxel" or not hasattr(target, k):
                ap.error(f"{kv!r}: expected KEY=VALUE with KEY a VoxelConfig or BuildConfig field")
            setattr(target, k, json.loads(v) if v[:1] in '0123456789-[{tfn".' else v)
        for k in ("min_track", "max_landmarks"):
            if getattr(args, k) is not None:
                setattr(build_cfg, k, getattr(args, k))
        if args.iterations:
            build_cfg.voxel.iterations = args.iterations
        # construct again: the defaults that follow the fields set (exact_poses: refine_window, align_patches)
        build_cfg = dataclasses.replace(build_cfg)
        build_cfgs.append((vname, build_cfg))
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    splits: list[Split] = []
    if args.map or args.queries:
        from favormap.io import read_sequence

        if not (args.map and args.queries):
            ap.error("--map and --queries go together")
        mapping, queries = read_sequence(args.map), read_sequence(args.queries)
        splits.append(Split("custom", mapping, queries, nearest_view_angle(queries, mapping)))
    else:
        which = args.splits.split(",")
        real = [w for w in which if w in REAL_SPLITS or w in EXTRA_SPLITS or w in CROSS_SPLITS]
        if args.suite or any(w not in ("fox-holdout", "fox-extrap") for w in real):
            splits += real_splits(real)
        else:
            splits += fox_splits(which, args.extrap_step)
        if "orbit" in which:
            splits.append(orbit_split(workdir, args.orbit_frames, 640, 480))
        if "orbit-dense" in which:
            splits.append(orbit_split(workdir, args.orbit_frames, 640, 480, dense=True))
    rows = []
    for sp in splits:
        rows += run_split(sp, args, build_cfgs)
    print(markdown(rows))
    real = real_rows(rows, splits)
    if real:
        print(
            "\nReal sets, favormap (rendered, noise priors; median over prior seeds "
            + ",".join(map(str, args.prior_seeds))
            + ") and the baseline (median over RANSAC seeds "
            + ",".join(map(str, args.baseline_seeds))
            + ") on the same queries:\n"
        )
        print(real_table(real))
    paired = paired_table(rows)
    if paired:
        print("\n" + paired)
    if len(train_seeds) > 1:
        print("\nAcross training seeds " + ", ".join(map(str, train_seeds)) + ":\n")
        print(seed_table(rows, build_cfgs))
    if len(build_cfgs) > 1:
        print("\n" + seed_paired_table(rows, build_cfgs))
    builds = {
        (r["split"], r["extractor"] + r.get("solver_tag", "") + f" {r.get('map_variant', '')}".rstrip()): r["build_s"]
        for r in rows
        if "extractor" in r
    }
    build_cfg = build_cfgs[0][1]
    print(
        f"\n{len(splits)} splits in {time.perf_counter() - t0:.0f} s; build config: extractor {','.join(extractors)}, "
        f"min_track {build_cfg.min_track}, max_landmarks {build_cfg.max_landmarks}, "
        f"voxel solver {','.join(sorted({c.voxel.solver for _, c in build_cfgs}))} (adam: "
        f"{build_cfg.voxel.iterations} iterations x {build_cfg.voxel.rays_per_landmark} rays), "
        f"box factor {build_cfg.voxel.box_factor}, device {args.device}; map builds: "
        + ", ".join(f"{sp} {ex} {'reused' if b is None else f'{b:.0f} s'}" for (sp, ex), b in builds.items())
    )
    if args.json:
        write_rows(args.json, rows + ([{"real": real}] if real else []))


if __name__ == "__main__":
    sys.exit(main())
