#!/usr/bin/env python3
"""How well do rendered descriptors predict the descriptors extracted at novel views?

Renders a synthetic room sequence, builds a map from every ``--stride``-th frame, and at novel
views (the other frames, or random views between the poses when stride is 1) compares, for every
visible landmark, the descriptor truly extracted at its projection with
  - the descriptor rendered from the novel view (FaVoR),
  - the descriptor observed in the nearest training view that saw the landmark,
  - the landmark's mean observed descriptor.
Prints the mean cosine similarity of each to the truth.

    python tools/bench_novel_view.py [--stride 1] [--frames 31] [--extractor xfeat] [--iterations 120]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--frames", type=int, default=31)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--extractor", default="xfeat")
    ap.add_argument("--iterations", type=int, default=120)
    ap.add_argument("--resolution", type=int, default=3)
    args = ap.parse_args()

    from favormap import features
    from favormap.build import BuildConfig, build_map
    from favormap.geometry import camera_centers
    from favormap.io import load_image
    from favormap.ops.spatial import project_inside
    from favormap.synthetic import make_room, random_views_near, render, write_sequence
    from favormap.voxels import VoxelConfig, render_from_camera

    tmp = tempfile.TemporaryDirectory()
    full = write_sequence(Path(tmp.name) / "room", n_frames=args.frames, width=args.width, height=args.height)
    train_idx = list(range(0, len(full), args.stride))
    seq = full.subset(train_idx)
    cfg = BuildConfig(extractor=args.extractor, max_keypoints=1024, max_side=0, max_landmarks=400,
                      voxel=VoxelConfig(iterations=args.iterations, resolution=args.resolution))
    m = build_map(seq, cfg)
    cam = seq.cameras[0]
    scene = make_room(0)
    ex = features.create(m.extractor)
    if args.stride > 1:
        views = [f.cam_from_world for i, f in enumerate(full.frames) if i % args.stride]
    else:
        views = random_views_near([f.cam_from_world for f in seq.frames], 6, seed=3, max_trans=0.03,
                                  max_rot_deg=2.0, scene=scene)
    R3 = m.grid_resolution ** 3
    desc = torch.as_tensor(m.descriptors.reshape(m.num_landmarks, R3, -1))
    dens = torch.as_tensor(m.density.reshape(m.num_landmarks, R3))
    train_feats = [ex.extract(load_image(f.image_path, cam, 0)[0]) for f in seq.frames]
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]

    def project(T, X):
        x = X @ T[:3, :3].T + T[:3, 3]
        return x[:, :2] / x[:, 2:] * [fx, fy] + [cx, cy]

    sims = {"rendered": [], "nearest training view": [], "mean descriptor": []}
    for T in views:
        img, _ = render(scene, cam, T)
        qf = ex.extract(img)
        c = camera_centers(T)
        vis = np.flatnonzero(project_inside(m.positions, cam, T, margin_px=8))
        truth = ex.sample(qf, project(T, m.positions[vis]))
        rendered = render_from_camera(desc[vis], dens[vis], torch.as_tensor(m.positions[vis]).float(),
                                      torch.as_tensor(m.voxel_size[vis]), torch.as_tensor(c).float(),
                                      m.render_samples).numpy()
        # nearest training view among each landmark's observations (vectorised over observations)
        obs = np.isin(m.track_landmark, vis)
        lm, fr = m.track_landmark[obs], m.track_frame[obs]
        d = np.linalg.norm(camera_centers(m.cam_from_world[fr]) - c, axis=1)
        order = np.lexsort((d, lm))
        first = order[np.r_[True, lm[order][1:] != lm[order][:-1]]]
        nearest_frame = dict(zip(lm[first].tolist(), fr[first].tolist()))
        nearest = np.zeros_like(truth)
        for f in set(nearest_frame.values()):
            k = np.array([i for i, j in enumerate(vis) if nearest_frame[j] == f])
            nearest[k] = ex.sample(train_feats[f], project(m.cam_from_world[f], m.positions[vis[k]]))
        sims["rendered"].append(np.sum(rendered * truth, 1))
        sims["nearest training view"].append(np.sum(nearest * truth, 1))
        sims["mean descriptor"].append(np.sum(m.mean_descriptor[vis] * truth, 1))
    print(f"{len(views)} novel views, {m.num_landmarks} landmarks, extractor {args.extractor}, stride {args.stride}, "
          f"R={args.resolution}, {args.iterations} iterations")
    print(f"{'descriptor':<24} {'mean cosine to truth':>21}")
    for k, v in sims.items():
        print(f"{k:<24} {np.mean(np.concatenate(v)):>21.4f}")


if __name__ == "__main__":
    sys.exit(main())
