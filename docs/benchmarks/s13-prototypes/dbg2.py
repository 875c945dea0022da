# Session 13 prototype (2026-11-27), kept with the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md.
# Reads the maps/sequences that 'python tools/bench_accuracy.py --workdir /tmp/acc12' writes. Not part of the package.
import sys, numpy as np
sys.path.insert(0, "/work/main/tools")
import bench_accuracy as B
from pathlib import Path
from favormap.localize import Localizer, LocalizeConfig
from favormap.mapfile import Map
split = B.orbit_split(Path("/tmp/acc12"), 24, 640, 480)
m = Map.open("/tmp/acc12/orbit.h5")
a = Localizer(m, LocalizeConfig()); b = Localizer(m, LocalizeConfig(guided_sift_contrast=0.01))
fr = split.queries.frames[16]
img, cam = a.prepare(fr.image_path, split.queries.cameras[fr.camera_id])
fa = a.extractor.extract(img)
fb, mn, gn = b._strong_first(b.extractor.extract(img))
print(len(fa), len(fb), mn, gn)
print(np.abs(fb.keypoints[:mn] - fa.keypoints).max() if mn == len(fa) else "count differs")
print(np.abs(fb.descriptors[:mn] - fa.descriptors).max() if mn == len(fa) else "")
print(a.extractor._sift.getContrastThreshold(), b.extractor._sift.getContrastThreshold(), a.extractor.max_keypoints, b.extractor.max_keypoints)
