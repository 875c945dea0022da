#!/usr/bin/env python3
"""Extending a map against building it at once: localization of held-out frames and time.

The sequence (default ../shared/data/fox) is split: every 5th frame is held out as a query, the other
(mapping) frames in two halves A (the first) and B (the rest). Each repeat builds A + B at once (the
reference), builds A, extends the A map with B (favormap.ops.extend.extend_map), validates the extended
map and localizes the held-out frames with both maps (the default localizer, priors moved by 0.3 units /
10 degrees from the ground truth, as ``favormap eval``). Printed: per repeat and as medians over the
repeats, the median translation / rotation error of each map, the localized share, the landmarks and the
times (the extend's against the reference build's, each with the write of its map; building A is not part
of the extend's time).

    python tools/bench_extend.py                      # fox, 3 repeats
    python tools/bench_extend.py SEQ --repeat 5 --json out.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_accuracy import paired_ratio  # noqa: E402, I001  (tools/, on the path above)

FOX = ROOT.parent / "shared" / "data" / "fox"


def split(seq, every: int):
    n = len(seq)
    held = [i for i in range(n) if i % every == 0]
    mapping = [i for i in range(n) if i % every]
    half = len(mapping) // 2
    return seq.subset(held), seq.subset(mapping), seq.subset(mapping[:half]), seq.subset(mapping[half:])


def localize_errors(path: Path, queries, seed: int) -> np.ndarray:
    """(N, 2) translation / rotation errors of the held-out frames (inf: not localized)."""
    from favormap.geometry import pose_error
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.evaluate import EvalConfig, make_priors
    from favormap.mapfile import Map

    with Map.open(path) as m:
        loc = Localizer(m, LocalizeConfig())
        priors = make_priors(queries, m.rig_from_world, EvalConfig(prior_mode="noise", seed=seed))
        out = []
        for fr, prior in zip(queries.frames, priors):
            res = loc.localize(fr.image_path, prior, queries.cameras[fr.camera_id])
            out.append(pose_error(res.cam_from_world, fr.cam_from_world) if res.success else (np.inf, np.inf))
    return np.array(out)


def validate(path: Path) -> bool:
    r = subprocess.run([sys.executable, "-m", "favormap", "validate", str(path)], capture_output=True, text=True)
    return r.returncode == 0


def one_repeat(seq, args, k: int, work: Path) -> dict:
    from favormap.build import BuildConfig, build_map
    from favormap.mapfile import write_map
    from favormap.ops.extend import ExtendConfig, extend_map

    held, mapping, a, b = split(seq, args.every)
    cfg = BuildConfig()
    row = {"repeat": k}
    t = time.perf_counter()  # the build and the write of its map, as the extend's time counts its write
    full = build_map(mapping, cfg)
    write_map(full, work / "full.h5")
    row["full_s"] = time.perf_counter() - t
    row["full_landmarks"] = full.num_landmarks
    del full
    t = time.perf_counter()
    ma = build_map(a, cfg)
    row["a_s"] = time.perf_counter() - t
    write_map(ma, work / "a.h5")
    row["a_landmarks"] = ma.num_landmarks
    del ma
    t = time.perf_counter()
    s = extend_map(work / "a.h5", b, work / "ab.h5", ExtendConfig())
    row["extend_s"] = time.perf_counter() - t
    row["extend_timings"] = s.timings
    row.update(
        extended_landmarks=s.landmarks_after,
        grown=s.landmarks_grown,
        added=s.landmarks_added,
        removed=s.landmarks_removed,
        retrained=s.landmarks_retrained,
        observations_added=s.observations_added,
    )
    row["valid"] = validate(work / "ab.h5")
    for name, path in (("full", work / "full.h5"), ("a", work / "a.h5"), ("extended", work / "ab.h5")):
        e = localize_errors(path, held, seed=k)
        row[f"{name}_t"] = float(np.median(e[:, 0]))
        row[f"{name}_r"] = float(np.median(e[:, 1]))
        row[f"{name}_localized"] = float(np.mean(np.isfinite(e[:, 0])))
        row[f"{name}_errors"] = e.tolist()
    row["error_ratio"] = row["extended_t"] / row["full_t"]
    paired = paired_ratio(np.array(row["extended_errors"])[:, 0], np.array(row["full_errors"])[:, 0], seed=k)
    row["paired_ratio"] = paired["ratio"] if paired else float("nan")
    row["paired_ci95"] = paired["ci95"] if paired else [float("nan")] * 2
    row["time_ratio"] = row["extend_s"] / row["full_s"]
    return row


def table(rows: list[dict]) -> str:
    head = (
        f"{'repeat':>6} | {'full: med t':>11} {'rot':>6} {'loc':>4} {'lms':>5} {'s':>6} | "
        f"{'A: med t':>9} {'loc':>4} | {'extended: med t':>15} {'rot':>6} {'loc':>4} {'lms':>5} {'grown':>5} "
        f"{'s':>6} | {'t ratio':>7} {'time ratio':>10} {'valid':>5}"
    )
    lines = [head, "-" * len(head)]

    def fmt(r, label):
        return (
            f"{label:>6} | {r['full_t']:11.5f} {r['full_r']:6.3f} {100 * r['full_localized']:3.0f}% "
            f"{r['full_landmarks']:5.0f} {r['full_s']:6.1f} | {r['a_t']:9.5f} {100 * r['a_localized']:3.0f}% | "
            f"{r['extended_t']:15.5f} {r['extended_r']:6.3f} {100 * r['extended_localized']:3.0f}% "
            f"{r['extended_landmarks']:5.0f} {r['grown']:5.0f} {r['extend_s']:6.1f} | {r['error_ratio']:7.3f} "
            f"{r['time_ratio']:10.3f} {str(r['valid']):>5}"
        )

    for r in rows:
        lines.append(fmt(r, str(r["repeat"])))
    keys = [k for k, v in rows[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    med = {k: float(np.median([r[k] for r in rows])) for k in keys}
    med["valid"] = all(r["valid"] for r in rows)
    lines.append("-" * len(head))
    lines.append(fmt(med, "median"))
    lines.append(
        f"median over {len(rows)} repeats: extended / full median translation error {med['error_ratio']:.3f} "
        f"(target <= 1.1), extend time / full build time {med['time_ratio']:.3f} (target <= 0.6)"
    )
    ci = rows[0]["paired_ci95"]
    lines.append(
        f"paired per query (repeat 0, queries both maps localize): extended / full translation error "
        f"{rows[0]['paired_ratio']:.3f} [{ci[0]:.3f}, {ci[1]:.3f}] (geometric mean, 95 % bootstrap interval)"
    )
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="?", default=str(FOX))
    ap.add_argument("--every", type=int, default=5, help="hold out frames 0, N, 2N, ... (default 5)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    from favormap.io import read_sequence

    seq = read_sequence(args.sequence)
    held, mapping, a, b = split(seq, args.every)
    print(
        f"{args.sequence}: {len(mapping)} mapping frames (A {len(a)}, B {len(b)}), {len(held)} held out",
        file=sys.stderr,
    )
    rows = []
    for k in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="bench-extend-") as tmp:
            rows.append(one_repeat(seq, args, k, Path(tmp)))
        r = rows[-1]
        print(
            f"repeat {k}: full {r['full_t']:.5f} in {r['full_s']:.1f} s, extended {r['extended_t']:.5f} in "
            f"{r['extend_s']:.1f} s {r['extend_timings']}",
            file=sys.stderr,
        )
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
