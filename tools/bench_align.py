"""Map alignment on real sequences, ``favormap.ops.align_maps`` against a known transform.

    PYTHONPATH=$PWD python tools/bench_align.py /work/shared/data/fox [--split halves|interleaved]
        [--quality quick] [--seed 0] [--json]
    PYTHONPATH=$PWD python tools/bench_align.py DESK_RECORDING --pair XYZ_RECORDING [--refine-poses]

One sequence: two maps of disjoint frames (the first and second half, or the even and odd frames), the
second's poses moved by a random similarity (the truth). ``--pair SEQ_B``: maps of two recordings whose
poses share one frame (the truth is the identity), e.g. the two TUM recordings of one desk.

The errors: the largest distance, over b's camera centres, between the centres moved by the estimate
and by the truth, as a fraction of the path extent (the diagonal of the bounding box of a's and b's
camera centres in a), the rotation difference in degrees, the scale's relative error, and the
translation's error per axis (for ``--pair``, in a's units); each also divided by its reported
standard deviation. ``--other SEQ`` also aligns a with a map of another sequence, which must be refused.
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
from favormap.geometry import camera_centers, rotation_angle_deg, rotvec_to_rotmat  # noqa: E402
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


def alignment_errors(r, T, centres_b, centres_a) -> dict:
    """The estimate's errors against the truth ``T`` (module docstring), and each in its reported stds."""
    pe = centres_b @ r.b_to_a[:3, :3].T + r.b_to_a[:3, 3]
    pt = centres_b @ T[:3, :3].T + T[:3, 3]
    extent = float(np.linalg.norm(np.ptp(np.concatenate([centres_a, pt]), axis=0)))
    s_true = float(np.cbrt(np.linalg.det(T[:3, :3])))
    rot = float(rotation_angle_deg((r.b_to_a[:3, :3] / r.scale) @ (T[:3, :3] / s_true).T))
    dt = r.b_to_a[:3, 3] - T[:3, 3]
    std_t = np.asarray(r.std_translation_xyz)
    return {
        "path_extent": extent,
        "error_fraction_of_extent": float(np.max(np.linalg.norm(pe - pt, axis=1)) / extent),
        "error_rotation_deg": rot,
        "error_scale": r.scale / s_true - 1,
        "error_translation": dt.tolist(),
        "true_scale": s_true,
        "rotation_sigmas": rot / r.std_rotation_deg,
        "scale_sigmas": abs(np.log(r.scale / s_true)) / r.std_log_scale,
        "translation_sigmas": (np.abs(dt) / std_t).tolist(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--split", choices=["halves", "interleaved"], default="halves")
    ap.add_argument("--quality", default="quick", help="voxel training preset of both builds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pair", metavar="SEQ_B", help="map b from this recording, in the same frame as the first")
    ap.add_argument("--refine-poses", action="store_true", help="build both maps with refined poses")
    ap.add_argument("--other", help="a sequence of another place: its map must be refused")
    ap.add_argument("--keep", metavar="DIR", help="write the two maps (a.h5, b.h5) and b_to_a_true.txt here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    seq = read_sequence(args.sequence)
    n = len(seq)
    if args.pair:
        seq_a, seq_b, T, split = seq, read_sequence(args.pair), np.eye(4), "pair"
    else:
        ia, ib = (range(0, n // 2), range(n // 2, n)) if args.split == "halves" else (range(0, n, 2), range(1, n, 2))
        centres = camera_centers(np.stack([f.cam_from_world for f in seq.frames]))
        T = random_similarity(np.random.default_rng(args.seed), float(np.linalg.norm(centres.max(0) - centres.min(0))))
        seq_a, seq_b, split = seq.subset(ia), moved_sequence(seq.subset(ib), T), args.split
    cfg = BuildConfig(voxel=VoxelConfig.preset(args.quality), refine_poses=args.refine_poses)
    out: dict = {"sequence": args.sequence, "pair": args.pair, "frames": [len(seq_a), len(seq_b)], "split": split}
    with tempfile.TemporaryDirectory() as tmp:
        if args.keep:
            tmp = args.keep
            Path(tmp).mkdir(parents=True, exist_ok=True)
            np.savetxt(Path(tmp) / "b_to_a_true.txt", T)
        a, b = Path(tmp) / "a.h5", Path(tmp) / "b.h5"
        t0 = time.perf_counter()
        ma, mb = build_map(seq_a, cfg), build_map(seq_b, cfg)
        write_map(ma, a)
        write_map(mb, b)
        out["build_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = align_maps(a, b)
        out["align_s"] = time.perf_counter() - t0
        # the maps' own (possibly refined) poses
        pb = camera_centers(np.asarray(mb.cam_from_world))
        pa = camera_centers(np.asarray(ma.cam_from_world))
        out.update(alignment_errors(r, T, pb, pa))
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
            f"{args.sequence}{' + ' + args.pair if args.pair else ''}: frames {out['frames']} ({split}), "
            f"builds {out['build_s']:.0f} s, align {out['align_s']:.1f} s\n"
            f"  matches {al['num_matches']}, inliers {al['num_inliers']} ({100 * al['inlier_ratio']:.0f} %); "
            f"refined on {al['num_refined_matches']} matches, {al['num_observations']} observations, "
            f"reprojection RMS {al['reprojection_rms_px']:.3g} px\n"
            f"  centres {100 * out['error_fraction_of_extent']:.4f} % of path extent {out['path_extent']:.3g}; "
            f"rotation {out['error_rotation_deg']:.4f} deg ({out['rotation_sigmas']:.1f} std); "
            f"scale {100 * out['error_scale']:+.4f} % ({out['scale_sigmas']:.1f} std); translation "
            + " ".join(f"{v:+.4g}" for v in out["error_translation"])
            + " ("
            + " ".join(f"{v:.1f}" for v in out["translation_sigmas"])
            + " std)"
        )
        if "other" in out:
            print(f"  other scene: {out['other']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
