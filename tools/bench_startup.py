#!/usr/bin/env python3
"""Start-up time of the command line: wall time of one-shot commands, each a fresh process.

    python tools/bench_startup.py [--workdir DIR] [--runs 5]

Renders a 30-frame 640x480 synthetic room and builds a map with up to 1500 landmarks into
``--workdir`` (kept and reused by later runs), then times, each ``--runs`` times in a fresh
``python -m favormap`` process: ``--help``, ``info``, ``validate``, a one-shot ``localize`` of one
640x480 image with a prior (target: <= 1.5 s wall on two CPU cores), and the batch form
(``localize map queries/ --priors``) over 10 images, per query. Also prints which heavy modules
each command imports and what the one-shot localize spends on imports (``python -X importtime``).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HEAVY = ["torch", "open3d", "pycolmap", "cv2", "h5py", "scipy", "rerun", "trimesh", "tqdm", "xfeat"]
TARGET_LOCALIZE_S = 1.5
N_BATCH = 10


def prepare(work: Path, iterations: int) -> tuple[Path, Path, Path, Path, Path]:
    import cv2

    from favormap.build import BuildConfig, build_map
    from favormap.geometry import inverse, perturb_pose
    from favormap.mapfile import Map, write_map
    from favormap.synthetic import make_room, random_views_near, render, write_sequence

    work.mkdir(parents=True, exist_ok=True)
    path, query_dir = work / "room.h5", work / "queries"
    seq = (
        write_sequence(work / "room", n_frames=30, width=640, height=480)
        if not (work / "room" / "sequence.json").is_file()
        else __import__("favormap.io", fromlist=["read_sequence"]).read_sequence(work / "room")
    )
    if not path.is_file():
        t = time.perf_counter()
        cfg = BuildConfig(max_landmarks=1500)
        cfg.voxel.iterations = iterations  # training length does not change what a localization reads or renders
        write_map(build_map(seq, cfg), path)
        print(f"built {path} in {time.perf_counter() - t:.1f} s")
    with Map.open(path) as m:
        print(f"map: {m.num_landmarks} landmarks, {m.num_frames} frames")
    query_dir.mkdir(exist_ok=True)
    scene = make_room(0)
    views = random_views_near([f.cam_from_world for f in seq.frames], N_BATCH, seed=1, scene=scene)
    rng = np.random.default_rng(0)
    lines = []
    for i, T in enumerate(views):
        img = query_dir / f"q{i:02d}.png"
        if not img.is_file():
            cv2.imwrite(str(img), cv2.cvtColor(render(scene, seq.cameras[0], T)[0], cv2.COLOR_RGB2BGR))
        prior = inverse(perturb_pose(T, 0.3, 15, rng))
        lines.append(f"{img.name} " + " ".join(f"{v:.12g}" for v in prior.ravel()))
    (work / "priors.txt").write_text("\n".join(lines) + "\n")
    prior_file = work / "prior.txt"
    prior_file.write_text(" ".join(lines[0].split()[1:]) + "\n")
    return path, query_dir / "q00.png", prior_file, query_dir, work / "priors.txt"


def run(argv: list[str], env: dict) -> tuple[float, str]:
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "favormap", *argv], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    if r.returncode not in (0, 2):
        raise SystemExit(f"favormap {' '.join(argv)} failed: {r.stderr.strip()}")
    return wall, r.stdout


def loaded_modules(argv: list[str], env: dict) -> list[str]:
    code = (
        "import sys\nfrom favormap.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        f"print('LOADED', ','.join(h for h in {HEAVY!r} if h in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, env=env)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("LOADED")), "LOADED ?")
    return [m for m in line.split(" ", 1)[1].split(",") if m]


def import_times(argv: list[str], env: dict) -> list[tuple[str, float]]:
    """Cumulative import time (s) of the top-level packages the command imports, largest first."""
    r = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "favormap", *argv], capture_output=True, text=True, env=env
    )
    out = {}
    for ln in r.stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \| (\s*)(\S+)$", ln)
        if m and "." not in m.group(3):
            out[m.group(3)] = max(out.get(m.group(3), 0), int(m.group(1)) / 1e6)
    return sorted(out.items(), key=lambda kv: -kv[1])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default="favormap-bench-startup", help="map and queries (kept, reused)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=200, help="voxel training iterations of the map (default 200)")
    args = ap.parse_args()
    env = {**os.environ, "RERUN_ANALYTICS": "false"}
    path, img, prior, qdir, priors = prepare(Path(args.workdir), args.iterations)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"python {sys.version.split()[0]}, {cores} CPU cores available, load average {os.getloadavg()[0]:.1f}")
    cases = [
        ("--help", ["--help"], None),
        ("info", ["info", str(path)], None),
        ("validate", ["validate", str(path)], None),
        (
            "localize (one image)",
            ["localize", str(path), str(img), "--prior", str(prior), "--device", "cpu"],
            TARGET_LOCALIZE_S,
        ),
        (
            f"localize (folder of {N_BATCH}), per query",
            ["localize", str(path), str(qdir), "--priors", str(priors), "--device", "cpu"],
            None,
        ),
    ]
    print(f"\n{'command':<34} {'median s':>9} {'min s':>7} {'target s':>9}  heavy imports")
    results = {}
    for name, argv, target in cases:
        walls, out = [], ""
        for _ in range(args.runs):
            w, out = run(argv, env)
            walls.append(w / (N_BATCH if "folder" in name else 1))
        med = statistics.median(walls)
        results[name] = (med, out)
        mods = loaded_modules(argv, env)
        tgt = f"{target:.2f}" if target else "-"
        flag = "" if not target else ("  ok" if med <= target else "  OVER")
        print(f"{name:<34} {med:9.3f} {min(walls):7.3f} {tgt:>9}{flag}  {' '.join(mods) or '-'}")
    out = results["localize (one image)"][1]
    timings = re.search(r"timings \(ms\): (.*)", out)
    print("\none-shot localize, in-process timings (ms): " + (timings.group(1) if timings else "?"))
    print(
        "one-shot localize, import time by package (s, cumulative): "
        + ", ".join(f"{k} {v:.2f}" for k, v in import_times(cases[3][1], env)[:8])
    )


if __name__ == "__main__":
    main()
