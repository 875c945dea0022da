"""Capture the final weighted refinement's inputs per query (fox splits), with query keypoint sizes."""
import sys, pickle, numpy as np
sys.path.insert(0, '/work/main/tools')
import bench_accuracy as B
from favormap.localize import Localizer, LocalizeConfig
from favormap.localize import localizer as LZ
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.mapfile import Map

cap = []
orig = LZ.Localizer._weighted
def patched(self, q, it, last, t):
    inl = last["matches"][last["inliers"]]
    f = q.feats
    assert np.allclose(f.keypoints, f.dense.xy)
    Xcov = LZ.landmark_covariances(self.map, inl[:, 0], self._landmark_sigma(inl[:, 0]))
    by_desc = last["by_descriptor"][last["inliers"]] if "by_descriptor" in last else None
    cap.append(dict(rows=inl[:, 0].copy(), pose0=it.cam_from_world.copy(), X=self.positions[inl[:, 0]].copy(), kp=f.keypoints[inl[:, 1]].copy(),
                    size=f.dense.size[inl[:, 1]].copy(), octave=f.dense.octave[inl[:, 1]].copy(), Xcov=Xcov, K=q.cam.K.copy(), by_desc=by_desc))
    return orig(self, q, it, last, t)
LZ.Localizer._weighted = patched

out = {}
for split in B.fox_splits(["fox-extrap", "fox-holdout"]):
    for seed in ["", "-s1", "-s2"]:
        m = Map.open(f"/tmp/acc15/{split.name}{seed}.h5")
        priors = make_priors(split.queries, m.cam_from_world, EvalConfig(prior_mode="noise", seed=0))
        loc = Localizer(m, LocalizeConfig())
        rows = []
        for i, fr in enumerate(split.queries.frames):
            cap.clear()
            res = loc.localize(fr.image_path, priors[i], split.queries.cameras[fr.camera_id])
            d = dict(cap[-1]); d.update(gt=fr.cam_from_world, est=res.cam_from_world, ok=res.success)
            rows.append(d)
        out[split.name + seed] = rows
        err = [np.linalg.norm(B.__dict__.get('np').linalg.inv(r['gt'])[:3,3] - np.linalg.inv(r['est'])[:3,3]) for r in rows]
        print(split.name + seed, np.median(err), flush=True)
        m.close()
pickle.dump(out, open('/tmp/s19/cap.pkl', 'wb'))
