import pickle, sys, numpy as np
sys.path.insert(0, "/work/main")
from favormap.geometry import project
for fn in sys.argv[1:]:
    o = pickle.load(open(fn, "rb"))
    p = o["pairs"]; X = o["positions"]; v = o["view_dir"]
    t_star = np.empty(len(p["q"])); along_px = np.empty(len(p["q"]))
    for i in np.unique(p["q"]):
        s = p["q"] == i
        L = p["lm"][s]
        eps = 1e-3 * o["depth"][L]
        uv0 = project(o["qK"][i], o["qT"][i], X[L]); uv1 = project(o["qK"][i], o["qT"][i], X[L] + eps[:, None] * v[L])
        g = (uv1 - uv0) / eps[:, None]  # px per unit move toward the cameras
        r = p["xy"][s] - uv0
        # least-squares move along the view dir that explains the residual, in units of depth
        t_star[s] = (r * g).sum(1) / np.maximum((g * g).sum(1), 1e-12) / o["depth"][L]
        along_px[s] = np.linalg.norm(g, axis=1) * o["depth"][L] * 0.01  # px for 1 % of depth
    good = along_px > 0.5  # the query sees depth changes
    ang = o["angle"][p["lm"]]
    print(fn, "pairs", good.sum(), "median signed depth move (fraction of depth, + = toward cameras) %.4f" % np.median(t_star[good]))
    for lo, hi in ((0, 3), (3, 6), (6, 10), (10, 20), (20, 90)):
        sel = good & (ang >= lo) & (ang < hi)
        if sel.sum() > 20:
            print(f"   angle {lo}-{hi}: n {sel.sum()} median {np.median(t_star[sel]):+.4f} mean(trimmed) {np.mean(np.clip(t_star[sel], -0.05, 0.05)):+.4f}  frac>0 {np.mean(t_star[sel] > 0):.2f}")
    L = o["length"][p["lm"]]
    for lo, hi in ((3, 4), (4, 6), (6, 9), (9, 99)):
        sel = good & (L >= lo) & (L < hi)
        print(f"   length {lo}-{hi}: n {sel.sum()} median {np.median(t_star[sel]):+.4f} frac>0 {np.mean(t_star[sel] > 0):.2f}")
