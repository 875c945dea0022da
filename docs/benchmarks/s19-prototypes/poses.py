"""Estimated poses of every fox query with rendered / mean / nearest-view descriptors (seeds 0-2)."""
import sys, pickle, numpy as np, dataclasses as dc
sys.path.insert(0, '/work/main/tools')
import bench_accuracy as B
from favormap.localize import Localizer, LocalizeConfig, make_source
from favormap.localize.descriptors import observation_descriptors
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.mapfile import Map
out = {}
splits = sys.argv[1].split(',') if len(sys.argv) > 1 else ["fox-extrap", "fox-holdout"]
for split in B.fox_splits(splits):
    for seed in ["", "-s1", "-s2"]:
        m = Map.open(f"/tmp/acc15/{split.name}{seed}.h5")
        priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
        obs_desc = observation_descriptors(m, split.mapping)
        for src in ["rendered", "mean", "nearest"]:
            cfg = dc.replace(LocalizeConfig(), descriptors=src)
            loc = Localizer(m, cfg, descriptor_source=make_source(src, m, cfg.device, obs_desc))
            res = []
            for i, fr in enumerate(split.queries.frames):
                r = loc.localize(fr.image_path, priors[i], split.queries.cameras[fr.camera_id])
                cov = r.covariance
                res.append(dict(gt=fr.cam_from_world, est=r.cam_from_world, ok=r.success, n=r.num_inliers,
                                cov=None if cov is None else (cov.center, cov.rotation, cov.landmark_scale, cov.keypoint_sigma_px)))
            out[(split.name, seed, src)] = res
            e = [np.linalg.norm(np.linalg.inv(q['gt'])[:3, 3] - np.linalg.inv(q['est'])[:3, 3]) for q in res]
            print(split.name, seed or '-s0', src, round(np.median(e) * 1000, 2), flush=True)
        m.close()
pickle.dump(out, open(f'/tmp/s19/poses-{"_".join(splits)}.pkl', 'wb'))
