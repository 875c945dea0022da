# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
import sys, cv2, json
sys.path.insert(0, "/work/main/tools")
import bench_accuracy as B
import favormap.features.sift as S
from favormap.build import build_map, BuildConfig
from favormap.mapfile.writer import write_map
c = float(sys.argv[1]); which = sys.argv[2]
orig = S.SIFTExtractor.__init__
def init(self, *a, **k):
    orig(self, *a, **k)
    self._sift = cv2.SIFT_create(nfeatures=self.max_keypoints, contrastThreshold=c)
S.SIFTExtractor.__init__ = init
split = B.fox_splits([which])[0]
m = build_map(split.mapping, BuildConfig())
print(which, m.provenance["stats"], m.provenance["timings"])
write_map(m, f"/tmp/s13/{which}-c{c}.h5")
