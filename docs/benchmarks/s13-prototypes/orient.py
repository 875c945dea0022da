# Session 13 prototype (2026-11-27), kept with the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md.
# Reads the maps/sequences that 'python tools/bench_accuracy.py --workdir /tmp/acc12' writes. Not part of the package.
"""Does nfeatures=0 (cap ourselves) make the kept orientation independent of the threshold?"""
import numpy as np, cv2, glob
from favormap.features import sift as S
imgs = sorted(glob.glob("/tmp/acc12/orbit_queries/images/*.png"))[14:18] + sorted(glob.glob("/work/shared/data/fox/images/*.jpg"))[3:6]
def load(p):
    img = cv2.cvtColor(cv2.imread(p), cv2.COLOR_BGR2RGB)
    if img.shape[1] > 640:
        s = 640 / max(img.shape[:2]); img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return img
for nf in ("capped", "uncapped"):
    for mk in (2048, 4096):
        diffs = []
        for p in imgs:
            img = load(p)
            out = []
            for c in (0.02, 0.01):
                ex = S.SIFTExtractor(max_keypoints=mk, contrast_threshold=c)
                if nf == "uncapped":
                    ex._sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=c)
                f = ex.extract(img)
                out.append(f)
            a, b = out
            strong = b.scores >= 0.02 / 3
            B = {tuple(x): d for x, d in zip(np.round(b.keypoints[strong], 2).tolist(), b.descriptors[strong])}
            common = [(d, B[tuple(x)]) for x, d in zip(np.round(a.keypoints, 2).tolist(), a.descriptors) if tuple(x) in B]
            diff = np.mean([np.abs(d1 - d2).max() > 1e-4 for d1, d2 in common])
            diffs.append(f"{len(a)}/{len(common)}/{diff:.3f}")
        print(nf, mk, diffs)
