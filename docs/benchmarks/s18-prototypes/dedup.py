"""Eighteenth session: SIFT patch points that OpenCV describes alike (share of the fox build's points),
and the training rays with and without describing each distinct point once (identical? time on two cores)."""
import time
import numpy as np
from scipy.spatial import cKDTree
from favormap.build import BuildConfig, ExtractorSpec, extract_sequence, track_frames, triangulate_tracks, select_landmarks, training_rays
from favormap.features.base import patch_offsets
from favormap.features.sift import octave_of_size
from favormap.features.sift import unpack_octave
from favormap.geometry import project
from favormap.io import read_sequence
seq = read_sequence('/work/shared/data/fox')
cfg = BuildConfig()
ff = extract_sequence(seq, ExtractorSpec('sift', cfg.max_keypoints), cfg.max_side)
lms = select_landmarks(triangulate_tracks(track_frames(ff, cfg), ff, cfg), cfg.max_landmarks)
tr = lms.tracks; tid = tr.track_of_obs; fi = tr.frame_idx
Ks = np.stack([c.K for c in ff.cameras]); T = ff.cam_from_world
uv = project(Ks[fi], T[fi], lms.positions[tid])
pix = uv[:, None, :] + patch_offsets(7)[None]
tot = uniq = 0
for f in range(len(ff.features)):
    sel = fi == f
    pts = pix[sel].reshape(-1, 2).astype(np.float32)
    st = ff.features[f].dense
    size = np.full(len(pts), 12.0, np.float32); angle = np.zeros(len(pts), np.float32); octv = np.full(len(pts), int(octave_of_size(12.0)), np.int64)
    d, nn = cKDTree(st.xy.astype(np.float64)).query(pts.astype(np.float64)); near = d <= 4.0
    size[near], angle[near], octv[near] = st.size[nn[near]], st.angle[nn[near]], st.octave[nn[near]]
    h, w = st.gray.shape
    p = pts - 0.5; p[:, 0] = np.clip(p[:, 0], 0, w - 1); p[:, 1] = np.clip(p[:, 1], 0, h - 1)
    scale = unpack_octave(octv)[2]
    c = np.rint(p * scale[:, None]).astype(np.int64)
    key = np.stack([c[:, 0], c[:, 1], octv, size.view(np.int32), angle.view(np.int32)], 1)
    tot += len(key); uniq += len(np.unique(key, axis=0))
print('points', tot, 'unique', uniq, 'share %.3f' % (uniq / tot))

# ---- the build-level check (training_rays with and without grouping)
import favormap.features.sift as S
spec = ExtractorSpec('sift', cfg.max_keypoints)
t = time.perf_counter(); a = training_rays(lms, ff, spec, 7).targets; ta = time.perf_counter() - t
real = S._distinct
S._distinct = lambda p, *r: (np.arange(len(p)), np.arange(len(p)))
t = time.perf_counter(); b = training_rays(lms, ff, spec, 7).targets; tb = time.perf_counter() - t
print('dedup %.2f s, without %.2f s, identical %s' % (ta, tb, np.array_equal(a, b)))
S._distinct = real
t = time.perf_counter(); a = training_rays(lms, ff, spec, 7).targets; ta = time.perf_counter() - t
print('dedup again %.2f s' % ta)
