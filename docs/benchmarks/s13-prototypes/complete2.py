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
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
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
lms0 = triangulate(tracks, ff.cam_from_world, Ks, tc)

def descs(l):
    tr = l.tracks; tid = tr.track_of_obs
    D = np.zeros((len(l), 128))
    for f in range(len(ff.features)):
        m = tr.frame_idx == f
        np.add.at(D, tid[m], ff.features[f].descriptors[tr.keypoint_idx[m]])
    return D / np.linalg.norm(D, axis=1, keepdims=True)

def complete(l, r, smin, merge=True, max_merge_px=2.0):
    tr = l.tracks; tid = tr.track_of_obs; D = descs(l)
    fi, ki, xy, t = [tr.frame_idx], [tr.keypoint_idx], [tr.xy], [tid]
    pairs = []
    for f in range(len(ff.features)):
        F = ff.features[f]
        uv, z = project(Ks[f], ff.cam_from_world[f], l.positions, with_depth=True)
        W, H = F.image_size
        inf = tr.frame_idx == f
        have = np.zeros(len(l), bool); have[tid[inf]] = True
        owner = np.full(len(F), -1); owner[tr.keypoint_idx[inf]] = tid[inf]
        cand = np.flatnonzero(~have & (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < W) & (uv[:, 1] < H))
        d = np.linalg.norm(uv[cand, None] - F.keypoints[None], axis=2)
        k = d.argmin(1); dk = d[np.arange(len(cand)), k]
        s = np.einsum("ij,ij->i", D[cand], F.descriptors[k])
        ok = (dk <= r) & (s >= smin)
        c, k, s = cand[ok], k[ok], s[ok]
        free = owner[k] < 0
        if merge:
            pairs.append(np.stack([c[~free], owner[k[~free]]], 1))
        c, k, s = c[free], k[free], s[free]
        o = np.lexsort((-s, k)); first = np.r_[True, k[o][1:] != k[o][:-1]] if len(o) else np.zeros(0, bool)
        c, k = c[o][first], k[o][first]
        fi.append(np.full(len(c), f)); ki.append(k); xy.append(F.keypoints[k].astype(np.float64)); t.append(c)
    fi, ki, xy, t = map(np.concatenate, (fi, ki, xy, t))
    label = np.arange(len(l))
    if merge and pairs:
        P = np.concatenate(pairs)
        if len(P):
            g = coo_matrix((np.ones(len(P)), (P[:, 0], P[:, 1])), shape=(len(l), len(l)))
            _, label = connected_components(g, directed=False)
    t2 = label[t]
    # drop duplicate (track, frame) obs: keep the first (original obs come first)
    key = t2.astype(np.int64) * len(ff.features) + fi
    _, first = np.unique(key, return_index=True)
    sel = np.sort(first)
    ext = Tracks.from_obs(fi[sel], ki[sel], xy[sel], t2[sel])
    out = triangulate(ext, ff.cam_from_world, Ks, tc)
    return out

def evaluate(l, name):
    s = select_landmarks(l, 3000)
    r = lm.residuals(qff, s.positions, descs(s))
    print(which, name, f"lms {len(l)} sel len {s.tracks.lengths.mean():.2f}", lm.summary(r, ""), flush=True)

evaluate(lms0, "base")
for r, smin, merge in [(3, 0.8, False), (3, 0.8, True), (4, 0.7, True)]:
    l = complete(lms0, r, smin, merge)
    evaluate(l, f"complete r{r} s{smin} merge{merge}")
    l = complete(l, r, smin, merge)
    evaluate(l, f"  x2")
