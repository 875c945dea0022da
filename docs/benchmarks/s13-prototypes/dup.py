# Session 13 prototype (2026-11-27), kept with the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md.
# Reads the maps/sequences that 'python tools/bench_accuracy.py --workdir /tmp/acc12' writes. Not part of the package.
import numpy as np, glob
from favormap import features
from favormap.io import load_image
import cv2
imgs = sorted(glob.glob("/tmp/acc12/orbit_queries/images/*.png"))[:6] + sorted(glob.glob("/work/shared/data/fox/images/*.jpg"))[20:23]
a_ex = features.create("sift", max_keypoints=4096); b_ex = features.create("sift", max_keypoints=4096, contrast_threshold=0.01)
for p in imgs:
    img = cv2.cvtColor(cv2.imread(p), cv2.COLOR_BGR2RGB)
    if img.shape[1] > 640:
        s = 640 / max(img.shape[:2]); img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    a, b = a_ex.extract(img), b_ex.extract(img)
    strong = b.scores >= 0.02 / 3
    A = {tuple(x) for x in np.round(a.keypoints, 2).tolist()}
    B = {tuple(x) for x in np.round(b.keypoints[strong], 2).tolist()}
    print(p.split("/")[-1], len(a), len(b), strong.sum(), "common", len(A & B), "only default", len(A - B), "only strong-low", len(B - A), "min a score", a.scores.min())
