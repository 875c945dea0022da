# Session 14 prototype (2026-11-27): SIFT patch descriptors, serial vs threads, on the GPU machine's 16 cores.
# Run from the repository root with .gpu/ prepared (bash tools/gpu_check.sh prepare). Not part of the package.
import glob, time, threading, numpy as np, cv2
from concurrent.futures import ThreadPoolExecutor
from favormap.features.sift import SIFTExtractor
from favormap.features import patch_offsets
files = sorted(glob.glob(".gpu/fox/images/*"))[:16]
imgs = []
for f in files:
    im = cv2.cvtColor(cv2.imread(f), cv2.COLOR_BGR2RGB)
    h, w = im.shape[:2]; s = 640 / max(h, w)
    imgs.append(cv2.resize(im, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA))
exs = {}
def ex():
    k = threading.get_ident()
    if k not in exs: exs[k] = SIFTExtractor(max_keypoints=2048)
    return exs[k]
feats = [ex().extract(im) for im in imgs]
pts = [(f.keypoints[:600][:, None, :] + patch_offsets(7, 1)[None]).reshape(-1, 2) for f in feats]
print("frames", len(feats), "points per frame", len(pts[0]))
def one(i): return ex().sample(feats[i], pts[i])
for label, cvthreads, workers in [("serial, OpenCV 16", 16, 1), ("serial, OpenCV 1", 1, 1), ("16 threads, OpenCV 1", 1, 16), ("8 threads, OpenCV 1", 1, 8), ("16 threads, OpenCV 16", 16, 16)]:
    cv2.setNumThreads(cvthreads)
    t = time.perf_counter()
    if workers == 1:
        for i in range(len(feats)): one(i)
    else:
        with ThreadPoolExecutor(workers) as p: list(p.map(one, range(len(feats))))
    dt = time.perf_counter() - t
    print(f"{label:<24} {dt:6.2f} s  ({1e6 * dt / sum(map(len, pts)):.1f} us per descriptor)")
# where a single-thread sample call goes
cv2.setNumThreads(1)
import cProfile, pstats
cProfile.run("one(0)", "/tmp/p.prof"); pstats.Stats("/tmp/p.prof").sort_stats("tottime").print_stats(5)
