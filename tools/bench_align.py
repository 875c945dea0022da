"""Map alignment on a real sequence: two maps of disjoint halves, the second's poses moved by a random
similarity, ``favormap.ops.align_maps`` between them, its error against the truth.

    PYTHONPATH=$PWD python tools/bench_align.py /work/shared/data/fox [--split halves|interleaved]
        [--quality quick] [--seed 0] [--json]

The error is the largest distance, over the second half's camera centres, between the centres moved
by the estimate and by the truth, as a fraction of the path extent (the diagonal of the bounding box
of all camera centres), and the rotation difference in degrees. ``--other SEQ`` also aligns the first
half with a map of another sequence, which must be refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from favormap.build import BuildConfig, build_map  # noqa: E402
from favormap.errors import FavormapError  # noqa: E402
from favormap.geometry import camera_centers, rotvec_to_rotmat  # noqa: E402
from favormap.io import read_sequence  # noqa: E402
from favormap.mapfile import write_map  # noqa: E402
from favormap.ops import align_maps  # noqa: E402
from favormap.voxels import VoxelConfig  # noqa: E402


def moved_sequence(seq, b_to_a):
    """``seq`` (frame a) with its poses expressed in frame b, where x_a = b_to_a x_b."""
    s = float(np.cbrt(np.linalg.det(b_to_a[:3, :3])))
    frames = []
    for f in seq.frames:
        cfw = f.cam_from_world @ b_to_a
        cfw[:3, :] /= s
        frames.append(dataclasses.replace(f, cam_from_world=cfw))
    return dataclasses.replace(seq, frames=frames)


def random_similarity(rng, extent: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.exp(rng.uniform(-1, 1)) * rotvec_to_rotmat(rng.normal(size=3))
    T[:3, 3] = rng.normal(size=3) * extent
    return T


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--split", choices=["halves", "interleaved"], default="halves")
    ap.add_argument("--quality", default="quick", help="voxel training preset of both builds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--other", help="a sequence of another place: its map must be refused")
    ap.add_argument("--keep", metavar="DIR", help="write the two maps (a.h5, b.h5) and b_to_a_true.txt here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    seq = read_sequence(args.sequence)
    n = len(seq)
    ia, ib = (range(0, n // 2), range(n // 2, n)) if args.split == "halves" else (range(0, n, 2), range(1, n, 2))
    centres = camera_centers(np.stack([f.cam_from_world for f in seq.frames]))
    extent = float(np.linalg.norm(centres.max(0) - centres.min(0)))
    T = random_similarity(np.random.default_rng(args.seed), extent)
    cfg = BuildConfig(voxel=VoxelConfig.preset(args.quality))
    out: dict = {"sequence": args.sequence, "frames": n, "split": args.split, "path_extent": extent}
    with tempfile.TemporaryDirectory() as tmp:
        if args.keep:
            tmp = args.keep
            Path(tmp).mkdir(parents=True, exist_ok=True)
            np.savetxt(Path(tmp) / "b_to_a_true.txt", T)
        a, b = Path(tmp) / "a.h5", Path(tmp) / "b.h5"
        t0 = time.perf_counter()
        write_map(build_map(seq.subset(ia), cfg), a)
        write_map(build_map(moved_sequence(seq.subset(ib), T), cfg), b)
        out["build_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = align_maps(a, b)
        out["align_s"] = time.perf_counter() - t0
        pb = camera_centers(np.stack([f.cam_from_world for f in moved_sequence(seq.subset(ib), T).frames]))
        pe = pb @ r.b_to_a[:3, :3].T + r.b_to_a[:3, 3]
        pt = pb @ T[:3, :3].T + T[:3, 3]
        Re, Rt = r.b_to_a[:3, :3] / r.scale, T[:3, :3] / np.cbrt(np.linalg.det(T[:3, :3]))
        out["error_fraction_of_extent"] = float(np.max(np.linalg.norm(pe - pt, axis=1)) / extent)
        out["error_rotation_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(Re @ Rt.T) - 1) / 2, -1, 1))))
        out["true_scale"] = float(np.cbrt(np.linalg.det(T[:3, :3])))
        out["alignment"] = r.to_dict()
        if args.other:
            c = Path(tmp) / "other.h5"
            write_map(build_map(read_sequence(args.other), cfg), c)
            try:
                align_maps(a, c)
                out["other"] = "aligned (should have been refused)"
            except FavormapError as e:
                out["other"] = f"refused: {e}"
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        al = out["alignment"]
        print(
            f"{args.sequence}: {n} frames ({args.split}), builds {out['build_s']:.0f} s, align {out['align_s']:.2f} s\n"
            f"  matches {al['num_matches']}, inliers {al['num_inliers']} ({100 * al['inlier_ratio']:.0f} %), "
            f"rms {al['rms']:.4g}\n"
            f"  error {100 * out['error_fraction_of_extent']:.3f} % of path extent {extent:.3g}, "
            f"{out['error_rotation_deg']:.4f} deg; bootstrap std rot {al['std_rotation_deg']:.3g} deg, "
            f"log-scale {al['std_log_scale']:.2g}"
        )
        if "other" in out:
            print(f"  other scene: {out['other']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
