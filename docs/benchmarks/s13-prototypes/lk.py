# Session 13 prototype (2026-11-27), kept so that the figures quoted in docs/benchmarks/accuracy-2026-11-27-s13.md
# can be re-measured: run from a folder holding landmark_metric.py, with the maps of
# 'python tools/bench_accuracy.py --workdir /tmp/acc12 --train-seeds 0,1,2' in /tmp/acc12. Not part of the package.
import sys, numpy as np, cv2
sys.path.insert(0, "/tmp/s13")
import landmark_metric as lm
from favormap.io import read_sequence
from favormap.build import extract_sequence, ExtractorSpec, select_landmarks
from favormap.tracking import track_features, Tracks
from favormap.triangulation import triangulate, TriangulationConfig
seq = read_sequence("/work/shared/data/fox"); n = len(seq); half = n // 2
splits = {"extrap": (list(range(half)), list(range(half, n))),
          "holdout": ([i for i in range(n) if i % 5], list(range(0, n, 5)))}
which = sys.argv[1]
mi, qi = splits[which]
qff = lm.query_features(seq.subset(qi))
ff = extract_sequence(seq.subset(mi), ExtractorSpec("sift", 2048), 640)
Ks = np.stack([c.K for c in ff.cameras])
tc = TriangulationConfig(5.0, 1.0, min_track=3)
tracks = track_features(ff.features, ff.cam_from_world, ff.cameras, 3, 3, 2.0, 0.7)
gray = [f.dense.gray for f in ff.features]

def descs(l):
    tr = l.tracks; tid = tr.track_of_obs
    D = np.zeros((len(l), 128))
    for f in range(len(ff.features)):
        m = tr.frame_idx == f
        np.add.at(D, tid[m], ff.features[f].descriptors[tr.keypoint_idx[m]])
    return D / np.linalg.norm(D, axis=1, keepdims=True)

def lk_refine(tr, win=15, levels=1, max_move=1.5, anchor="mid"):
    tid = tr.track_of_obs
    L = tr.lengths
    if anchor == "mid":
        a_obs = tr.offsets[:-1] + L // 2
    else:
        a_obs = tr.offsets[:-1]
    a = a_obs[tid]
    xy = tr.xy.copy()
    moved = np.zeros(len(xy), bool)
    fa, fb = tr.frame_idx[a], tr.frame_idx
    todo = np.flatnonzero(a != np.arange(len(xy)))
    key = fa[todo] * 10000 + fb[todo]
    for kk in np.unique(key):
        sel = todo[key == kk]
        A, B = int(fa[sel[0]]), int(fb[sel[0]])
        p0 = (tr.xy[a[sel]] - 0.5).astype(np.float32).reshape(-1, 1, 2)
        p1 = (tr.xy[sel] - 0.5).astype(np.float32).reshape(-1, 1, 2)
        out, st, err = cv2.calcOpticalFlowPyrLK(gray[A], gray[B], p0, p1.copy(), winSize=(win, win), maxLevel=levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01), flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        out = out.reshape(-1, 2) + 0.5
        ok = (st.ravel() == 1) & (np.linalg.norm(out - tr.xy[sel], axis=1) <= max_move)
        xy[sel[ok]] = out[ok]; moved[sel[ok]] = True
    return Tracks(tr.frame_idx, tr.keypoint_idx, xy, tr.offsets), moved

def evaluate(l, name):
    s = select_landmarks(l, 3000)
    r = lm.residuals(qff, s.positions, descs(s))
    print(which, name, f"lms {len(l)} reproj {np.median(l.reproj_errors):.3f}", lm.summary(r, ""), flush=True)

base = triangulate(tracks, ff.cam_from_world, Ks, tc)
evaluate(base, "base")
for kw in [dict(), dict(win=21), dict(win=11), dict(anchor="first")]:
    t2, moved = lk_refine(tracks, **kw)
    l = triangulate(t2, ff.cam_from_world, Ks, tc)
    evaluate(l, f"lk {kw} moved {moved.mean():.2f} shift {np.median(np.linalg.norm(t2.xy-tracks.xy,axis=1)[moved]):.2f}")
