"""Two orbit maps' landmarks: distance to the synthetic room's true surface by track length (the
twenty-seventh session's landmark_surface.py, for favormap maps only). Usage, from the repository
root: PYTHONPATH=. python docs/benchmarks/s28-prototypes/surface_by_track.py A.h5 B.h5 ..."""

import sys

import numpy as np

from favormap.mapfile.reader import Map
from favormap.synthetic import make_room
from favormap.synthetic.render import surface_distance

scene = make_room(0)
bins = [(3, 4), (5, 7), (8, 11), (12, 10**9)]
for path in sys.argv[1:]:
    m = Map(path)
    d = surface_distance(scene, m.positions)
    tl = np.asarray(m.track_length)
    parts = [f"all {len(d)}: {np.median(d):.5f}"]
    for lo, hi in bins:
        sel = (tl >= lo) & (tl <= hi)
        parts.append(f"{lo}-{hi if hi < 10**9 else ''}: {sel.sum()} / {np.median(d[sel]) if sel.any() else float('nan'):.5f}")
    print(path, " | ".join(parts))
