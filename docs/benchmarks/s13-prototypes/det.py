# Session 13 prototype (2026-11-27), kept with the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md.
# Reads the maps/sequences that 'python tools/bench_accuracy.py --workdir /tmp/acc12' writes. Not part of the package.
import numpy as np, cv2, glob
from favormap import features
img = cv2.cvtColor(cv2.imread(sorted(glob.glob("/tmp/acc12/orbit_queries/images/*.png"))[16]), cv2.COLOR_BGR2RGB)
ex = features.create("sift", max_keypoints=4096)
ref = ex.extract(img)
for k in range(6):
    f = features.create("sift", max_keypoints=4096).extract(img) if k % 2 else ex.extract(img)
    same_pos = len(f) == len(ref) and np.array_equal(f.keypoints, ref.keypoints)
    print(k, len(f), same_pos, np.abs(f.descriptors - ref.descriptors).max() if same_pos else "-")
cv2.setNumThreads(1)
f1 = features.create("sift", max_keypoints=4096).extract(img)
print("1 thread", len(f1), np.array_equal(f1.keypoints, ref.keypoints), np.abs(f1.descriptors - ref.descriptors).max() if len(f1) == len(ref) else "-")
# how many locations have several orientations
raw = cv2.SIFT_create(nfeatures=4096, contrastThreshold=0.02).detect(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
xy = np.round(np.array([k.pt for k in raw]) * 10).astype(int)
_, cnt = np.unique(xy[:, 0] * 100000 + xy[:, 1], return_counts=True)
print("raw", len(raw), "locations", len(cnt), "with >1 orientation", (cnt > 1).sum())
