#!/usr/bin/env python3
"""Maps from images without poses, against maps from the shipped poses, on real sets.

    python tools/bench_sfm.py [--sets fox,tum-desk] [--workdir DIR] [--reuse] [--priors 3] [--json OUT]

For each set, every 5th frame is held out as a query and the rest are the mapping frames (the
accuracy suite's holdout split). Two maps are built from the mapping frames with the build defaults:
one with the shipped poses, one with poses estimated from the images alone (favormap.io.sfm, the
poses withheld: what ``favormap build PHOTOS/`` does; exhaustive matching for the fox's 32 photos,
sequential for the TUM recording). The estimated frame is put onto the shipped one by the similarity
of the mapping cameras' centres (Umeyama); its residual says how well the two sets of poses agree.
Each query is then localized against both maps from the same noise priors (10 % of the path extent
and 10 deg off the shipped pose, moved into the estimated frame by the similarity for its map), each
query's result the median over ``--priors`` priors, and its error measured in the shipped frame. The
table gives the pose estimation's time, the alignment residual, both maps' median errors and the
paired ratio (geometric mean over the queries of the estimated-pose map's error over the
shipped-pose map's, with its 95 % bootstrap interval).
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

# name -> (folder, matcher): the sets measured
SETS = {
    "fox": (FOX, "exhaustive"),
    "tum-desk": (DATA / "tum_fr1_desk_xyz" / "rgbd_dataset_freiburg1_desk", "sequential"),
}
HOLDOUT = 5
PRIOR_SHARE, PRIOR_DEG = 0.10, 10.0  # the noise priors: share of the path extent, degrees


def holdout_split(name: str, root: Path) -> Split:
    from favormap.io import read_sequence

    seq = read_sequence(root)
    n = len(seq)
    return Split(name, seq.subset([i for i in range(n) if i % HOLDOUT]), seq.subset(list(range(0, n, HOLDOUT))))


def estimate(split: Split, workdir: Path, matcher: str, threads: int | None):
    """The SfmResult of the mapping frames' images, their shipped poses withheld."""
    from favormap.io.sfm import SfmOptions, estimate_poses

    folders = {Path(f.image_path).parent for f in split.mapping.frames}
    if len(folders) != 1:
        raise SystemExit(f"{split.name}: the mapping images lie in {len(folders)} folders; one expected")
    names = [Path(f.image_path).name for f in split.mapping.frames]
    opts = SfmOptions(matcher=matcher, image_names=names, threads=threads)
    return estimate_poses(folders.pop(), workdir / f"{split.name}.sfm", opts)


def alignment(sfm, split: Split) -> tuple[np.ndarray, np.ndarray]:
    """(S, residuals): the similarity taking the estimated mapping camera centres onto the shipped ones, and
    each registered camera's distance from its shipped centre after it (shipped units)."""
    from favormap.geometry import camera_centers, transform_points, umeyama

    shipped = {Path(f.image_path).name: f.cam_from_world for f in split.mapping.frames}
    est = camera_centers(np.stack([f.cam_from_world for f in sfm.sequence.frames]))
    gt = camera_centers(np.stack([shipped[f.name] for f in sfm.sequence.frames]))
    S = umeyama(est, gt)
    return S, np.linalg.norm(transform_points(S, est) - gt, axis=1)


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

    root, matcher = SETS[name]
    split = holdout_split(name, root)
    centres = camera_centers(np.stack([f.cam_from_world for f in split.mapping.frames]))
    extent = float(np.linalg.norm(np.ptp(centres, axis=0)))
    print(f"{name}: {len(split.mapping)} mapping frames, {len(split.queries)} queries", file=sys.stderr)
    sfm = estimate(split, args.workdir, matcher, args.threads)
    S, residual = alignment(sfm, split)
    config = BuildConfig(threads=args.threads)
    shipped_map, _ = build_or_load(split, args.workdir, config, args.reuse, tag="-shipped")
    sfm_split = Split(name, sfm.sequence, split.queries)
    t = time.perf_counter()
    sfm_map, _ = build_or_load(sfm_split, args.workdir, config, False, tag="-estimated")
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
        "sfm_seconds": round(sfm.seconds, 1),
        "sfm_reprojection_px": round(sfm.mean_reprojection_error_px, 3),
        "estimated_map_build_seconds": round(build_s, 1),
        "path_extent": round(extent, 4),
        "alignment_scale": round(float(np.cbrt(np.linalg.det(S[:3, :3]))), 5),
        "alignment_residual_median": float(np.median(residual)),
        "alignment_residual_max": float(residual.max()),
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
        "| set | registered | SfM s | residual (median / max, % of path) | shipped-pose map: localized, median "
        "t / R | estimated-pose map: localized, median t / R | ratio [95 % CI] |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b, x = r["shipped"], r["estimated"], r["ratio"]
        pct = 100 / r["path_extent"]
        ratio = "n/a" if x is None else f"{x['ratio']:.3f} [{x['ci95'][0]:.3f}, {x['ci95'][1]:.3f}]"
        out.append(
            f"| {r['set']} | {r['registered']}/{r['mapping_frames']} | {r['sfm_seconds']:.0f} | "
            f"{r['alignment_residual_median'] * pct:.2f} / {r['alignment_residual_max'] * pct:.2f} | "
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
    ap.add_argument("--reuse", action="store_true", help="reuse the shipped-pose maps of an earlier run")
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
