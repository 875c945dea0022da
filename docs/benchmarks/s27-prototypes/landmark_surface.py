"""The orbit map's landmarks against the pycolmap baseline's points: distance to the true surface of the
synthetic room, by track length. Usage: PYTHONPATH=. python landmark_surface.py WORKDIR (a
tools/bench_accuracy.py --workdir with orbit.h5 and orbit_baseline/)."""

import sys

import numpy as np
import pycolmap

from favormap.mapfile.reader import Map
from favormap.synthetic import make_room
from favormap.synthetic.render import surface_distance

scene = make_room(0)
d = sys.argv[1]
m = Map(f"{d}/orbit.h5")
P = m.positions
rec = pycolmap.Reconstruction(f"{d}/orbit_baseline/sparse")
pts = np.array([p.xyz for p in rec.points3D.values()])
tlb = np.array([p.track.length() for p in rec.points3D.values()])
err = np.array([p.error for p in rec.points3D.values()])


def s(x):
    return f"median {np.median(x):.5f} p75 {np.percentile(x, 75):.5f} p90 {np.percentile(x, 90):.5f}"


print("favormap", len(P), s(surface_distance(scene, P)))
sd = surface_distance(scene, pts)
print("baseline", len(pts), s(sd))
o = np.argsort(-tlb)[:3000]
print("baseline 3000 longest", s(sd[o]), "reproj", np.median(err[o]))
for k in (2, 3, 4, 6, 10):
    sel = tlb >= k
    print(" baseline track>=", k, sel.sum(), s(sd[sel]))
sdf = surface_distance(scene, P)
print(
    "favormap track len pct",
    np.percentile(m.track_length, [10, 50, 90]),
    "baseline 3000 longest",
    np.percentile(tlb[o], [10, 50, 90]),
)
for lo, hi in ((3, 5), (5, 8), (8, 12), (12, 30)):
    sel = (m.track_length >= lo) & (m.track_length < hi)
    print(
        " favormap track",
        lo,
        hi,
        sel.sum(),
        s(sdf[sel]) if sel.any() else "",
        "reproj",
        np.median(m.reproj_error[sel]) if sel.any() else "",
    )
    sel = (tlb >= lo) & (tlb < hi)
    print(
        " baseline track",
        lo,
        hi,
        sel.sum(),
        s(sd[sel]) if sel.any() else "",
        "reproj",
        np.median(err[sel]) if sel.any() else "",
    )
