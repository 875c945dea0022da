# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
"""Quick localization harness: median t_err of the default localizer on a split, with SIFT query contrast variants."""
import sys, numpy as np, cv2
sys.path.insert(0, "/work/main/tools")
import bench_accuracy as B
import favormap.features.sift as S
from favormap.localize import Localizer, make_source, LocalizeConfig
from favormap.localize.evaluate import EvalConfig, make_priors
from favormap.mapfile import Map
from favormap.geometry import pose_error
split_name, mp = sys.argv[1], sys.argv[2]
contrasts = [float(c) for c in sys.argv[3].split(",")]
from pathlib import Path
split = B.orbit_split(Path("/tmp/acc12"), 24, 640, 480) if split_name == "orbit" else B.fox_splits([split_name])[0]
orig_init = S.SIFTExtractor.__init__
for c in contrasts:
    def init(self, *a, _c=c, **k):
        orig_init(self, *a, **k)
        self._sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=_c)
    S.SIFTExtractor.__init__ = init
    m = Map.open(mp)
    loc = Localizer(m, LocalizeConfig(), descriptor_source=make_source("rendered", m))
    priors = make_priors(split.queries, m.cam_from_world, EvalConfig())
    errs, inl, nk = [], [], []
    for fr, prior in zip(split.queries.frames, priors):
        res = loc.localize(fr.image_path, prior, split.queries.cameras[fr.camera_id])
        errs.append(pose_error(res.cam_from_world, fr.cam_from_world)[0] if res.success else np.inf)
        inl.append(int(res.inlier_mask.sum())); nk.append(len(res.keypoints))
    errs = np.array(errs)
    bins = ""
    if split.angle is not None and split_name == "orbit":
        bins = " ".join(f"{lo}-{hi}:{np.median(errs[(split.angle>=lo)&(split.angle<hi)]):.5f}" for lo, hi in [(0,10),(10,20),(20,40),(40,180)])
    print(bins)
    print(f"{split_name} contrast {c}: median {np.median(errs):.5f} p90 {np.percentile(errs, 90):.5f} loc {np.isfinite(errs).sum()}/{len(errs)} inliers {np.mean(inl):.0f} kps {np.mean(nk):.0f}", flush=True)
