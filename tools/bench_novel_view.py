#!/usr/bin/env python3
"""Rendered vs stored descriptors at novel views EXTRAPOLATED away from the mapping path.

A synthetic room with exact poses (favormap.synthetic) is mapped from a 30-frame segment of the
orbit path (640x480 by default); queries are rendered at views that leave that segment: further
along the orbit on both sides, raised / lowered cameras re-aimed at the same content, both
combined, plus a few views between the training poses. For every (query view, landmark) pair
where the landmark is inside the image and not occluded (depth test against the rendered depth
map), the truth is the descriptor the extractor computes at the landmark's projection in the query
image. Pairs are binned by the angle, at the landmark, between the query camera and the nearest
training camera that observed it. Per bin the table gives the mean cosine to the truth of

  - each voxel variant (rendered with favormap.voxels.render_from_camera, the localizer's path),
  - ``nearest training view``: the descriptor observed in the training view nearest in angle,
  - ``2 nearest views``: inverse-angle blend of the two nearest training observations,
  - ``mean descriptor``: the landmark's mean observed descriptor (what the map stores),

"view chg" is how much a method's descriptor of a landmark varies across the query views (mean
pairwise 1 - cosine; the truth's own figure is on the first row), and the training time of each
variant (CPU seconds of the training call, this machine, torch threads
as set by --threads; CPU rather than wall time so that figures stay comparable on a loaded
machine)
and the median cosine of its rendered vs extracted training patches (fit cos).

The expensive part (rendering, extraction, tracking, triangulation, training patches, query
truth) is cached in --cache, keyed by the scene settings; variants only train and render.

    python tools/bench_novel_view.py                       # default VoxelConfig + baselines
    python tools/bench_novel_view.py --variants all        # every variant of VARIANTS below
    python tools/bench_novel_view.py --variants paper,box12 --set iterations=400
    python tools/bench_novel_view.py --extractor sift --variants paper,default
    python tools/bench_novel_view.py --list                # names and settings of the variants

The current defaults' figures are in docs/measurements.md; the variants that lost are listed in
docs/implementation-notes.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BINS = [(0, 10), (10, 20), (20, 40), (40, 180)]
CACHE_VERSION = 4

# Every variant tried, kept in the table: name -> VoxelConfig overrides on top of the variant's base.
# "default" is VoxelConfig() (the fast preset: Adam) with prior_mean_deg resolved per extractor as in
# build_map (for SIFT = prior16-centre50-k1-mean10); "lstsq" the closed-form solver of the quick
# preset. The others start from PAPER,
# the training before this benchmark existed (Adam; box = S l/f, 200 iterations x 32 patch rays per
# landmark, no centre rays, no prior).
PAPER = dict(
    solver="adam",
    box_factor=7.0,
    iterations=200,
    rays_per_landmark=32,
    centre_rays=0.0,
    prior_rays=0,
    prior_kernel_deg=3.0,
    prior_mean_deg=0.0,
)
_P = dict(PAPER, prior_rays=16)  # with the view-extrapolation prior
VARIANTS: dict[str, dict] = {
    "default": {},
    # the closed-form solver (--quality quick) against the default Adam training
    "lstsq": dict(solver="lstsq"),
    "lstsq-prior0.5": dict(solver="lstsq", lstsq_prior_weight=0.5),
    "lstsq-prior1": dict(solver="lstsq", lstsq_prior_weight=1.0),
    "lstsq-ridge0.1": dict(solver="lstsq", lstsq_ridge=0.1),
    "lstsq-tv0.01": dict(solver="lstsq", lstsq_tv=0.01),
    # nearly opaque densities: a ray stops near where it enters the cube, so the closed form's
    # descriptor depends on the viewing direction (a cube map of descriptors over the surface nodes)
    "lstsq-dens5": dict(solver="lstsq", density_init=5.0),
    "lstsq-dens20": dict(solver="lstsq", density_init=20.0),
    "lstsq-dens20-p3": dict(solver="lstsq", density_init=20.0, patch_size=3),
    "paper": dict(PAPER),
    "box12": dict(PAPER, box_factor=12.0),
    "box12-it600": dict(PAPER, box_factor=12.0, iterations=600),
    "box12-R5": dict(PAPER, box_factor=12.0, resolution=5),
    "centre50": dict(PAPER, centre_rays=0.5),
    "centre80": dict(PAPER, centre_rays=0.8),
    "centre100": dict(PAPER, centre_rays=1.0),
    "box12-centre50": dict(PAPER, box_factor=12.0, centre_rays=0.5),
    "centre50-tv0.03": dict(PAPER, centre_rays=0.5, tv_weight=0.03, tv_from=0.0),
    "centre50-dens5": dict(PAPER, centre_rays=0.5, density_init=5.0),
    "centre50-dens0.2": dict(PAPER, centre_rays=0.5, density_init=0.2),
    "centre50-constlr": dict(PAPER, centre_rays=0.5, lr_final=1.0),
    "prior16": dict(_P),
    "prior16-centre50": dict(_P, centre_rays=0.5),
    "prior16-centre50-spread60": dict(_P, centre_rays=0.5, prior_spread_deg=60.0),
    "prior16-centre50-k1": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0),
    "prior16-centre50-k6": dict(_P, centre_rays=0.5, prior_kernel_deg=6.0),
    "prior32-centre50": dict(_P, centre_rays=0.5, prior_rays=32),
    "prior16-centre25": dict(_P, centre_rays=0.25),
    "prior16-centre50-box12": dict(_P, centre_rays=0.5, box_factor=12.0),
    "prior16-centre50-it400": dict(_P, centre_rays=0.5, iterations=400),
    "prior16-centre50-R5": dict(_P, centre_rays=0.5, resolution=5),
    "prior16-centre50-constlr": dict(_P, centre_rays=0.5, lr_final=1.0),
    "prior16-centre100-k1": dict(_P, centre_rays=1.0, prior_kernel_deg=1.0),
    "prior16-centre50-k1-w2": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0, prior_weight=2.0),
    "prior16-centre50-k1-zero": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0, init="zero"),
    "prior16-centre50-k0.5": dict(_P, centre_rays=0.5, prior_kernel_deg=0.5),
    "prior8-centre50-k1": dict(_P, centre_rays=0.5, prior_rays=8, prior_kernel_deg=1.0),
    "prior16-centre50-k1-box12": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0, box_factor=12.0),
    "prior16-centre50-k1-mean10": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0, prior_mean_deg=10.0),
    "prior16-centre50-k1-mean30": dict(_P, centre_rays=0.5, prior_kernel_deg=1.0, prior_mean_deg=30.0),
}


def _bin_label(lo, hi):
    return f"{lo}-{hi} deg" if hi < 180 else f">{lo} deg"


# ---------------------------------------------------------------------------------------------
# data preparation (cached)
# ---------------------------------------------------------------------------------------------
def query_poses(path, train_idx, scene, n_between=3):
    """Held-out views: extrapolated along the orbit, raised / lowered and re-aimed, both, and a few
    between the training poses. Returns a list of (kind, cam_from_world)."""
    from favormap import geometry
    from favormap.synthetic import random_views_near
    from favormap.synthetic.scene import UP

    def moved(T, dz, dfwd=0.0, look=1.8):
        """Camera moved by dz up and dfwd forward, re-aimed at the point ``look`` ahead of it."""
        wfc = geometry.inverse(T)
        eye, fwd = wfc[:3, 3], wfc[:3, 2]
        target = eye + look * fwd
        e = eye + np.array([0, 0, dz]) + dfwd * fwd
        return geometry.look_at(e, target, up=UP)

    lo, hi = train_idx[0], train_idx[-1]
    out = []
    for k in [lo - 20, lo - 15, lo - 10, lo - 5, hi + 4, hi + 8, hi + 12, hi + 16]:
        if 0 <= k < len(path):
            out.append(("orbit", path[k]))
    for k in [lo + 2, (lo + hi) // 2, hi - 2]:
        out.append(("raised", moved(path[k], 0.6)))
        out.append(("lowered", moved(path[k], -0.75)))
    for k in [lo - 18, lo - 12, hi + 10, hi + 16]:
        if 0 <= k < len(path):
            out.append(("orbit+raised", moved(path[k], 0.6)))
            out.append(("orbit+lowered", moved(path[k], -0.8)))
    for k in [lo + 5, hi - 5]:
        out.append(("closer", moved(path[k], -0.1, dfwd=0.6)))
    for T in random_views_near(
        [path[i] for i in train_idx], n_between, seed=5, max_trans=0.03, max_rot_deg=2.0, scene=scene
    ):
        out.append(("between", T))
    return [(k, T) for k, T in out if scene.camera_is_valid(geometry.camera_centers(T))]


def prepare(args) -> dict:
    from favormap import features
    from favormap.build import (
        BuildConfig,
        extract_sequence,
        select_landmarks,
        track_frames,
        training_rays,
        triangulate_tracks,
    )
    from favormap.geometry import camera_centers, sum_by_group
    from favormap.ops.spatial import project_inside
    from favormap.synthetic import camera_path, make_camera, make_room, render, write_sequence

    key = dict(
        v=CACHE_VERSION, w=args.width, h=args.height, n=args.train_frames, L=args.max_landmarks, ex=args.extractor
    )
    digest = hashlib.sha1(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    cache = Path(args.cache) / f"novel_view_{digest}.pkl"
    if cache.exists() and not args.refresh:
        with open(cache, "rb") as f:
            return pickle.load(f)

    t0 = time.perf_counter()
    scene = make_room(0)
    cam = make_camera(args.width, args.height)
    path = camera_path(70, step=0.05, seed=0)
    start = 20
    train_idx = list(range(start, start + args.train_frames))
    queries = query_poses(path, train_idx, scene)
    cfg = BuildConfig(extractor=args.extractor, max_keypoints=2048, max_side=0, max_landmarks=args.max_landmarks)
    ex = features.create(cfg.extractor, max_keypoints=cfg.max_keypoints)
    with tempfile.TemporaryDirectory() as tmp:
        seq = write_sequence(
            Path(tmp) / "room", poses=[path[i] for i in train_idx], width=args.width, height=args.height, scene=scene
        )
        ff = extract_sequence(seq, ex, cfg.max_side)
    lms = select_landmarks(triangulate_tracks(track_frames(ff, cfg), ff, cfg), cfg.max_landmarks)
    rays = training_rays(lms, ff, ex, cfg.voxel.patch_size, box_factor=1.0)  # sizes = min l / f
    X = lms.positions
    P = rays.ray_dirs.shape[1]
    obs_centres = rays.obs_origin
    obs_unit = obs_centres - X[rays.obs_landmark]
    obs_unit /= np.linalg.norm(obs_unit, axis=1, keepdims=True)
    mean_desc = sum_by_group(rays.patch_means(), rays.obs_landmark, len(X))
    mean_desc /= np.linalg.norm(mean_desc, axis=1, keepdims=True)
    first = np.searchsorted(rays.obs_landmark, np.arange(len(X)))
    counts = np.bincount(rays.obs_landmark, minlength=len(X))

    qs = []
    for kind, T in queries:
        img, depth = render(scene, cam, T)
        vis = np.flatnonzero(project_inside(X, cam, T, margin_px=8))
        Xc = X[vis] @ T[:3, :3].T + T[:3, 3]
        uv = Xc[:, :2] / Xc[:, 2:] * [cam.K[0, 0], cam.K[1, 1]] + cam.K[:2, 2]
        ui = np.clip(uv.astype(int), 0, [args.width - 1, args.height - 1])
        dz = depth[ui[:, 1], ui[:, 0]]
        ok = np.abs(dz - Xc[:, 2]) < 0.02 * Xc[:, 2] + 0.005  # not occluded
        vis, uv = vis[ok], uv[ok]
        truth = ex.sample(ex.extract(img), uv)
        c = camera_centers(T)
        u = c - X[vis]
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        # angle to every training observation of each visible landmark (ragged -> padded)
        n_max = counts[vis].max()
        idx = first[vis][:, None] + np.arange(n_max)[None]
        valid = np.arange(n_max)[None] < counts[vis][:, None]
        idx = np.where(valid, idx, first[vis][:, None])
        ang = np.degrees(np.arccos(np.clip(np.einsum("kd,kod->ko", u, obs_unit[idx]), -1, 1)))
        ang = np.where(valid, ang, 1e9)
        order = np.argsort(ang, axis=1)[:, :2]
        a2 = np.take_along_axis(ang, order, 1)
        o2 = np.take_along_axis(idx, order, 1)
        qs.append(
            dict(
                kind=kind,
                cam_from_world=T,
                center=c,
                vis=vis,
                truth=truth,
                angle=a2[:, 0],
                angle2=a2[:, 1],
                nearest_obs=o2[:, 0],
                second_obs=o2[:, 1],
            )
        )
    data = dict(
        rays=rays,
        positions=X,
        mean_desc=mean_desc.astype(np.float32),
        centre_targets=rays.targets[:, P // 2].astype(np.float32),
        queries=qs,
        key=key,
        train_frames=len(train_idx),
        prep_seconds=time.perf_counter() - t0,
    )
    Path(args.cache).mkdir(parents=True, exist_ok=True)
    with open(cache, "wb") as f:
        pickle.dump(data, f)
    return data


# ---------------------------------------------------------------------------------------------
# evaluation
# ---------------------------------------------------------------------------------------------
def binned(values: np.ndarray, angles: np.ndarray) -> list[float]:
    out = []
    for lo, hi in BINS:
        m = (angles >= lo) & (angles < hi)
        out.append(float(values[m].mean()) if m.any() else float("nan"))
    out.append(float(values.mean()))
    return out


def view_change(data, vecs: list) -> float:
    """Mean over landmarks seen by >= 2 queries of the mean pairwise 1 - cosine between the
    descriptors of one method at those queries: how much its prediction varies with the view."""
    by: dict[int, list] = {}
    for q, v in zip(data["queries"], vecs):
        for j, x in zip(q["vis"].tolist(), v):
            by.setdefault(j, []).append(x)
    out = []
    for xs in by.values():
        if len(xs) >= 2:
            X = np.stack(xs)
            X = X / np.linalg.norm(X, axis=1, keepdims=True)
            n = len(X)
            out.append(1.0 - ((X @ X.T).sum() - n) / (n * (n - 1)))
    return float(np.mean(out))


def baselines(data) -> dict[str, tuple]:
    """name -> (cosines to the truth of all pairs, per-query descriptors)."""
    ct, md = data["centre_targets"], data["mean_desc"]
    res = {"truth (extracted)": [], "nearest training view": [], "2 nearest views": [], "mean descriptor": []}
    for q in data["queries"]:
        a1, a2 = q["angle"][:, None], q["angle2"][:, None]
        w1 = np.where(np.isfinite(a2) & (a2 < 1e8), a2 / np.maximum(a1 + a2, 1e-9), 1.0)
        blend = w1 * ct[q["nearest_obs"]] + (1 - w1) * ct[q["second_obs"]]
        res["truth (extracted)"].append(q["truth"])
        res["nearest training view"].append(ct[q["nearest_obs"]])
        res["2 nearest views"].append(blend / np.linalg.norm(blend, axis=1, keepdims=True))
        res["mean descriptor"].append(md[q["vis"]])
    return {
        k: (np.concatenate([np.sum(x * q["truth"], 1) for x, q in zip(v, data["queries"])]), v) for k, v in res.items()
    }


def run_variant(data, overrides: dict, extractor: str):
    import torch

    from favormap.features import policy_of
    from favormap.voxels import VoxelConfig, render_from_camera, train_voxels

    cfg = VoxelConfig(**overrides)
    if cfg.prior_mean_deg is None:  # as build_map does
        cfg.prior_mean_deg = policy_of(extractor).view_prior_deg
    rays = dataclasses.replace(data["rays"], sizes=data["rays"].sizes * cfg.box_factor)
    t = time.process_time()
    grids = train_voxels(rays, cfg)
    train_s = time.process_time() - t  # CPU seconds: comparable under load (run with --threads 1)
    desc, dens = grids.descriptors, grids.density
    centers = torch.as_tensor(data["positions"], dtype=torch.float32)
    sizes = torch.as_tensor(rays.sizes, dtype=torch.float32)
    sims, vecs = [], []
    for q in data["queries"]:
        v = torch.as_tensor(q["vis"]).long()
        r = render_from_camera(
            desc[v], dens[v], centers[v], sizes[v], torch.as_tensor(q["center"]).float(), cfg.samples
        ).numpy()
        sims.append(np.sum(r * q["truth"], 1))
        vecs.append(r)
    return np.concatenate(sims), vecs, train_s, float(np.median(grids.cosine))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default="default", help="comma-separated names of VARIANTS, or 'all'")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="VoxelConfig override applied to every variant (repeatable)",
    )
    ap.add_argument("--list", action="store_true", help="list the variants and exit")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--train-frames", type=int, default=30)
    ap.add_argument("--max-landmarks", type=int, default=600)
    ap.add_argument("--extractor", default="xfeat")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", "1")))
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "favormap_bench"))
    ap.add_argument("--refresh", action="store_true", help="recompute the cached scene data")
    ap.add_argument("--json", help="also append the rows to this JSON-lines file")
    args = ap.parse_args()
    if args.list:
        for k, v in VARIANTS.items():
            print(f"{k:<22} {v}")
        return 0

    import torch

    torch.set_num_threads(args.threads)
    names = list(VARIANTS) if args.variants == "all" else [s.strip() for s in args.variants.split(",") if s.strip()]
    extra = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        extra[k] = json.loads(v) if v[:1] in '0123456789-[{tfn".' else v
    data = prepare(args)
    angles = np.concatenate([q["angle"] for q in data["queries"]])
    counts = [int(((angles >= lo) & (angles < hi)).sum()) for lo, hi in BINS] + [len(angles)]
    rows = [(k, binned(v, angles), view_change(data, vecs), None, None) for k, (v, vecs) in baselines(data).items()]
    for name in names:
        if name not in VARIANTS:
            raise SystemExit(f"unknown variant {name!r}; --list shows them")
        ov = {**VARIANTS[name], **extra}
        sims, vecs, train_s, train_cos = run_variant(data, ov, args.extractor)
        label = name + ("" if not extra else " " + ",".join(f"{k}={v}" for k, v in extra.items()))
        rows.append((label, binned(sims, angles), view_change(data, vecs), train_s, train_cos))
        print(f"  {label}: all {rows[-1][1][-1]:.4f}, train {train_s:.1f} s", file=sys.stderr, flush=True)

    L = len(data["positions"])
    print(
        f"{data['train_frames']} training frames {args.width}x{args.height}, {L} landmarks, {len(data['queries'])} "
        "query views, "
        f"extractor {args.extractor}, torch threads {args.threads}"
    )
    head = [_bin_label(*b) for b in BINS] + ["all"]
    print(
        f"{'mean cosine to truth':<34}"
        + "".join(f"{h:>10}" for h in head)
        + f"{'view chg':>10}{'cpu s':>8}{'fit cos':>9}"
    )
    print(f"{'pairs':<34}" + "".join(f"{c:>10d}" for c in counts))
    for label, vals, vc, ts, tc in rows:
        print(
            f"{label:<34}"
            + "".join(f"{v:>10.4f}" for v in vals)
            + f"{vc:>10.4f}"
            + (f"{ts:>8.1f}{tc:>9.3f}" if ts is not None else "")
        )
    if args.json:
        with open(args.json, "a") as f:
            for label, vals, vc, ts, tc in rows:
                f.write(
                    json.dumps(
                        dict(
                            variant=label,
                            bins=dict(zip(head, vals)),
                            view_change=vc,
                            train_s=ts,
                            fit_cos=tc,
                            key=data["key"],
                        )
                    )
                    + "\n"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
