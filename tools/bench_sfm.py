#!/usr/bin/env python3
"""Maps from images without poses, against maps from the shipped poses, on real sets.

    python tools/bench_sfm.py [--sets fox,tum-desk] [--workdir DIR] [--reuse] [--priors 3] [--json OUT]

For each set, every 5th frame is held out as a query and the rest are the mapping frames (the
accuracy suite's holdout split). Two maps are built from the mapping frames with the build defaults:
one with the shipped poses, one with poses estimated from the images alone (favormap.io.sfm, the
poses withheld: what ``favormap build PHOTOS/`` does; exhaustive matching for the fox's 32 photos,
sequential for the TUM recording; ``fox-camera``: the fox with its shipped camera given and held
fixed, as ``--camera`` does). The estimated frame is put onto the shipped one by the similarity of
the mapping cameras (their centres and orientations, Umeyama); its residual says how well the two
sets of poses agree. Each query is then localized against both maps from the same noise priors (10 %
of the path extent and 10 deg off the shipped pose, moved into the estimated frame by the similarity
for its map), each query's result the median over ``--priors`` priors, and its error measured in the
shipped frame. The table gives the pose estimation's time, the alignment residual, both maps' median
errors and the paired ratio (geometric mean over the queries of the estimated-pose map's error over
the shipped-pose map's, with its 95 % bootstrap interval). ``--reuse`` takes an earlier run's
reconstructions and maps from ``--workdir``.
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

from accuracy.report import paired_ratio  # noqa: E402
from accuracy.runners import build_or_load, median_over_priors  # noqa: E402
from accuracy.splits import DATA, FOX, Split  # noqa: E402

# name -> (folder, matcher, known camera): the sets measured; a known camera: the shipped one given to the pose
# estimation (--camera), held fixed, else estimated (one SIMPLE_RADIAL camera, COLMAP's default)
SETS = {
    "fox": (FOX, "exhaustive", False),
    "fox-camera": (FOX, "exhaustive", True),
    "tum-desk": (DATA / "tum_fr1_desk_xyz" / "rgbd_dataset_freiburg1_desk", "sequential", False),
}
HOLDOUT = 5
PRIOR_SHARE, PRIOR_DEG = 0.10, 10.0  # the noise priors: share of the path extent, degrees


def holdout_split(name: str, root: Path) -> Split:
    from favormap.io import read_sequence

    seq = read_sequence(root)
    n = len(seq)
    return Split(name, seq.subset([i for i in range(n) if i % HOLDOUT]), seq.subset(list(range(0, n, HOLDOUT))))


def estimate(split: Split, workdir: Path, matcher: str, camera, threads: int | None, reuse: bool):
    """The SfmResult of the mapping frames' images, their shipped poses withheld (``reuse``: an earlier run's)."""
    from favormap.io.sfm import MARKER, SfmOptions, estimate_poses, read_result

    out = workdir / f"{split.name}.sfm"
    if reuse and (out / MARKER).is_file():
        return read_result(out)
    folders = {Path(f.image_path).parent for f in split.mapping.frames}
    if len(folders) != 1:
        raise SystemExit(f"{split.name}: the mapping images lie in {len(folders)} folders; one expected")
    names = [Path(f.image_path).name for f in split.mapping.frames]
    opts = SfmOptions(matcher=matcher, camera=camera, image_names=names, threads=threads)
    return estimate_poses(folders.pop(), out, opts)


def scene_depth(sfm) -> float:
    """The median depth of the reconstruction's points in the cameras that see them (its units)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(sfm.reconstruction_path))
    depths = []
    for im in rec.images.values():
        T = im.cam_from_world().matrix()
        X = np.array([rec.point3D(p.point3D_id).xyz for p in im.points2D if p.has_point3D()])
        if len(X):
            depths.append(X @ T[2, :3] + T[2, 3])
    return float(np.median(np.concatenate(depths)))


def alignment(sfm, split: Split) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, centre residuals, rotation residuals in deg): the similarity taking the estimated mapping cameras onto
    the shipped ones, fitted to their centres and orientations (each camera's centre and three points the
    scene's median depth along its axes, Umeyama: the centres alone leave the rotation about a flat or straight
    path loose), and each registered camera's distance from its shipped centre after it (shipped units) and
    angle from its shipped orientation."""
    from favormap.geometry import camera_centers, move_poses, rotation_angle_deg, umeyama

    shipped = {Path(f.image_path).name: f.cam_from_world for f in split.mapping.frames}
    est = np.stack([f.cam_from_world for f in sfm.sequence.frames])
    gt = np.stack([shipped[f.name] for f in sfm.sequence.frames])
    c_est, c_gt = camera_centers(est), camera_centers(gt)
    scale = np.cbrt(np.linalg.det(umeyama(c_est, c_gt)[:3, :3]))  # the lever in each frame's units
    lever = scene_depth(sfm)
    src = np.concatenate([c_est[:, None], c_est[:, None] + lever * est[:, :3, :3]], 1).reshape(-1, 3)
    dst = np.concatenate([c_gt[:, None], c_gt[:, None] + lever * scale * gt[:, :3, :3]], 1).reshape(-1, 3)
    S = umeyama(src, dst)
    moved = move_poses(est, S)
    turn = rotation_angle_deg(np.einsum("nij,nkj->nik", moved[:, :3, :3], gt[:, :3, :3]))
    return S, np.linalg.norm(camera_centers(moved) - c_gt, axis=1), turn


def localize_all(map_path: Path, split: Split, S: np.ndarray | None, extent: float, n_priors: int) -> np.ndarray:
    """(Q, 2) errors (shipped units, deg; inf when not localized) of the queries against ``map_path``, whose
    frame is the shipped one moved by ``S^-1`` (None: the shipped frame itself)."""
    from favormap.geometry import move_poses, perturb_pose, pose_error
    from favormap.localize import Localizer

    to_map = np.eye(4) if S is None else np.linalg.inv(S)
    loc = Localizer(map_path)
    errs = []
    for q, fr in enumerate(split.queries.frames):
        rng = np.random.default_rng([q, 7])
        priors = [perturb_pose(fr.cam_from_world, PRIOR_SHARE * extent, PRIOR_DEG, rng) for _ in range(n_priors)]
        in_map = dataclasses.replace(fr, cam_from_world=move_poses(fr.cam_from_world, to_map))
        cam = split.queries.cameras[fr.camera_id] if S is None else None  # the estimated map: its own camera
        _, res = median_over_priors(loc, in_map, cam, [(move_poses(p, to_map), None) for p in priors])
        if res.success:
            est = res.cam_from_world if S is None else move_poses(res.cam_from_world, S)
            errs.append(pose_error(est, fr.cam_from_world))
        else:
            errs.append((np.inf, np.inf))
    loc.close()
    return np.array(errs)


def run_set(name: str, args) -> dict:
    from favormap.build import BuildConfig
    from favormap.geometry import camera_centers

    root, matcher, known = SETS[name]
    split = holdout_split(name, root)
    camera = next(iter(split.mapping.cameras.values())) if known else None
    centres = camera_centers(np.stack([f.cam_from_world for f in split.mapping.frames]))
    extent = float(np.linalg.norm(np.ptp(centres, axis=0)))
    print(f"{name}: {len(split.mapping)} mapping frames, {len(split.queries)} queries", file=sys.stderr)
    sfm = estimate(split, args.workdir, matcher, camera, args.threads, args.reuse)
    S, residual, turn = alignment(sfm, split)
    config = BuildConfig(threads=args.threads)
    shipped_map, _ = build_or_load(split, args.workdir, config, args.reuse, tag="-shipped")
    sfm_split = Split(name, sfm.sequence, split.queries)
    t = time.perf_counter()
    sfm_map, _ = build_or_load(sfm_split, args.workdir, config, args.reuse, tag="-estimated")
    build_s = time.perf_counter() - t
    e_shipped = localize_all(shipped_map, split, None, extent, args.priors)
    e_sfm = localize_all(sfm_map, split, S, extent, args.priors)
    ratio = paired_ratio(e_sfm[:, 0], e_shipped[:, 0])
    return {
        "set": name,
        "mapping_frames": len(split.mapping),
        "queries": len(split.queries),
        "registered": len(sfm.registered),
        "unregistered": sfm.unregistered,
        "matcher": sfm.matcher,
        "camera": "shipped, fixed" if known else "estimated",
        "sfm_seconds": round(sfm.seconds, 1),
        "sfm_reprojection_px": round(sfm.mean_reprojection_error_px, 3),
        "estimated_map_build_seconds": round(build_s, 1),
        "path_extent": round(extent, 4),
        "alignment_scale": round(float(np.cbrt(np.linalg.det(S[:3, :3]))), 5),
        "alignment_residual_median": float(np.median(residual)),
        "alignment_residual_max": float(residual.max()),
        "alignment_rotation_median_deg": float(np.median(turn)),
        "shipped": _stats(e_shipped),
        "estimated": _stats(e_sfm),
        "ratio": None if ratio is None else {k: ratio[k] for k in ("queries", "ratio", "ci95", "lower", "higher")},
    }


def _stats(e: np.ndarray) -> dict:
    ok = np.isfinite(e[:, 0])
    return {
        "localized": int(ok.sum()),
        "median_translation": float(np.median(e[ok, 0])) if ok.any() else None,
        "median_rotation_deg": float(np.median(e[ok, 1])) if ok.any() else None,
        "translation": [round(float(v), 6) for v in e[:, 0]],
    }


def table(rows: list[dict]) -> str:
    out = [
        "| set | registered | SfM s | residual: centres (median / max, % of path), rotation (median) | "
        "shipped-pose map: localized, median "
        "t / R | estimated-pose map: localized, median t / R | ratio [95 % CI] |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b, x = r["shipped"], r["estimated"], r["ratio"]
        pct = 100 / r["path_extent"]
        ratio = "n/a" if x is None else f"{x['ratio']:.3f} [{x['ci95'][0]:.3f}, {x['ci95'][1]:.3f}]"
        out.append(
            f"| {r['set']} | {r['registered']}/{r['mapping_frames']} | {r['sfm_seconds']:.0f} | "
            f"{r['alignment_residual_median'] * pct:.2f} / {r['alignment_residual_max'] * pct:.2f} %, "
            f"{r['alignment_rotation_median_deg']:.3f} deg | "
            f"{_cell(a, r['queries'])} | {_cell(b, r['queries'])} | {ratio} |"
        )
    return "\n".join(out)


def _cell(s: dict, queries: int) -> str:
    if s["median_translation"] is None:
        return f"{s['localized']}/{queries}"
    return f"{s['localized']}/{queries}, {s['median_translation']:.4f} / {s['median_rotation_deg']:.3f} deg"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="fox", help=f"comma-separated: {', '.join(SETS)} (default fox)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/favormap-bench-sfm"))
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="reuse an earlier run's reconstructions and maps (pose estimation time: the earlier run's)",
    )
    ap.add_argument("--priors", type=int, default=3, help="noise priors per query (default 3)")
    ap.add_argument("--threads", type=int, default=None, help="threads of pose estimation and build")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.sets.split(","):
        if name not in SETS:
            raise SystemExit(f"unknown set {name!r} (choose from {', '.join(SETS)})")
        if not SETS[name][0].exists():
            print(f"(skipping {name}: {SETS[name][0]} not found)", file=sys.stderr)
            continue
        rows.append(run_set(name, args))
        print(table(rows[-1:]), file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
