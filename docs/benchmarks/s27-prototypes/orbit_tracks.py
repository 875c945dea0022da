"""Tracks of the orbit's mapping frames under tracking variants (window, conflicts, epipolar limit,
similarity). Usage: PYTHONPATH=. python orbit_tracks.py WORKDIR/orbit_map."""

import sys
import time

import numpy as np

from favormap.build import BuildConfig, ExtractorSpec, extract_sequence, track_frames, triangulate_tracks
from favormap.io import read_sequence

seq = read_sequence(sys.argv[1])
cfg = BuildConfig()
ff = extract_sequence(seq, ExtractorSpec(cfg.extractor, cfg.max_keypoints), cfg.max_side)
for kw in [
    dict(),
    dict(match_window=20),
    dict(match_window=24),
    dict(split_conflicts=True),
    dict(match_window=24, split_conflicts=True),
    dict(max_epipolar_px=2.0),
    dict(min_similarity=0.6),
]:
    c = BuildConfig(**kw)
    t0 = time.time()
    tr = track_frames(ff, c)
    dt = time.time() - t0
    L = tr.lengths() if callable(getattr(tr, "lengths", None)) else tr.lengths
    lms = triangulate_tracks(tr, ff, c)
    ll = np.asarray(lms.track_length) if hasattr(lms, "track_length") else None
    print(
        kw,
        f"{dt:.1f}s tracks {len(tr)} len>=12 {(L >= 12).sum()} median {np.median(L)} landmarks {len(lms)}",
        "lm len>=12",
        None if ll is None else (ll >= 12).sum(),
        "matches",
        tr.matches,
        tr.epipolar_matches,
    )
