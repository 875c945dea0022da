# Session 13 prototype (2026-11-27), kept with the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md.
# Reads the maps/sequences that 'python tools/bench_accuracy.py --workdir /tmp/acc12' writes. Not part of the package.
import sys, numpy as np
sys.path.insert(0, "/work/main/tools")
import bench_accuracy as B
from pathlib import Path
from favormap.localize import Localizer, make_source, LocalizeConfig
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.mapfile import Map
from favormap.geometry import pose_error
split = B.orbit_split(Path("/tmp/acc12"), 24, 640, 480)
m = Map.open("/tmp/acc12/orbit.h5")
priors = make_priors(split.queries, m.cam_from_world, EvalConfig())
cfgs = {"default": {}, "guided": dict(guided_sift_contrast=0.01), "matching": dict(sift_contrast=0.01, guided_sift_contrast=0.02)}
locs = {k: Localizer(m, LocalizeConfig(**v), descriptor_source=make_source("rendered", m)) for k, v in cfgs.items()}
for i in (5, 6, 16, 19, 22, 7, 17, 20):
    fr, prior = split.queries.frames[i], priors[i]
    out = []
    for k, loc in locs.items():
        r = loc.localize(fr.image_path, prior, split.queries.cameras[fr.camera_id])
        out.append(f"{k}: {pose_error(r.cam_from_world, fr.cam_from_world)[0]:.6f} kp {len(r.keypoints)} it {[ (it.kind, it.num_inliers) for it in r.iterations]} inl {r.num_inliers}")
    print(i, round(float(split.angle[i]), 1), *out, sep="\n   ")
