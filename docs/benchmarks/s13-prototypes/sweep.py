# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
import sys, numpy as np
sys.path.insert(0, "/tmp/s13")
import landmark_metric as lm
from favormap.io import read_sequence
from favormap.build import extract_sequence, ExtractorSpec, select_landmarks
from favormap.tracking import track_features, Tracks
from favormap.triangulation import triangulate, TriangulationConfig
from favormap.geometry import project
seq = read_sequence("/work/shared/data/fox"); n = len(seq); half = n // 2
splits = {"extrap": (list(range(half)), list(range(half, n))),
          "holdout": ([i for i in range(n) if i % 5], list(range(0, n, 5)))}
which = sys.argv[1]
mi, qi = splits[which]
qff = lm.query_features(seq.subset(qi))
ffs = {}
def landmarks(max_kp=2048, window=3, min_track=3, nsel=3000, sel="len"):
    if max_kp not in ffs:
        ffs[max_kp] = extract_sequence(seq.subset(mi), ExtractorSpec("sift", max_kp), 640)
    ff = ffs[max_kp]
    tracks = track_features(ff.features, ff.cam_from_world, ff.cameras, min_track, window, 2.0, 0.7)
    Ks = np.stack([c.K for c in ff.cameras])
    lms = triangulate(tracks, ff.cam_from_world, Ks, TriangulationConfig(5.0, 1.0, min_track=min_track))
    if sel == "len":
        s = select_landmarks(lms, nsel)
    tr = s.tracks; tid = tr.track_of_obs
    D = np.zeros((len(s), 128))
    for f in range(len(ff.features)):
        m = tr.frame_idx == f
        np.add.at(D, tid[m], ff.features[f].descriptors[tr.keypoint_idx[m]])
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return s, D
for kw in [dict(), dict(max_kp=4096), dict(max_kp=8192), dict(window=6), dict(max_kp=4096, window=6)]:
    s, D = landmarks(**kw)
    r = lm.residuals(qff, s.positions, D)
    print(which, kw, f"tracks len {s.tracks.lengths.mean():.2f}", lm.summary(r, ""), flush=True)
