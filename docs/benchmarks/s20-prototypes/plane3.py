import sys, pickle, numpy as np
sys.path.insert(0, "/work/main")
from scipy.spatial import cKDTree
from favormap.geometry import project
from favormap.localize.refine import reprojection_pixel_sigma
exec(open("/tmp/s20/plane.py").read().split("def spread_deg")[0].split("from scipy.spatial import cKDTree")[1])

def fuse2(o, k=20, gate=3.0, scale=3.0, mode="cons", keff_cap=None, rough_floor=0.0):
    X = o["positions"]; v = o["view_dir"]; n = o["n"]
    sig = np.maximum(reprojection_pixel_sigma(o["mre"], o["length"]), 0.2) * scale
    f = float(np.median(o["mK"][:, 0, 0]))
    m = np.maximum(o["length"], 2)
    across = o["depth"] * sig / (f * np.sqrt(m))
    va = (across / np.sin(np.radians(np.clip(o["angle"], 0.5, 90)))) ** 2
    nb = cKDTree(X).query(X, k + 1)[1][:, 1:]
    w = 1 / va[nb]; w /= w.sum(1, keepdims=True)
    c = np.einsum("nk,nki->ni", w, X[nb]); Q = X[nb] - c[:, None]
    ev, evec = np.linalg.eigh(np.einsum("nk,nki,nkj->nij", w, Q, Q))
    nrm = evec[:, :, 0]; cos = np.einsum("ni,ni->n", nrm, v); safe = np.where(np.abs(cos) < 1e-6, 1e-6, cos)
    tp = np.einsum("ni,ni->n", nrm, c - X) / safe
    # neighbours' noise along the normal: their along-variance times cos^2 of their ray with the normal
    cn = np.einsum("nki,ni->nk", v[nb], nrm) ** 2
    noise = np.einsum("nk,nk->n", w, va[nb] * cn)
    if mode == "cons":
        vp = (ev[:, 0] + np.einsum("nk,nk->n", w, va[nb])) / safe**2
    else:
        keff = 1 / np.sum(w**2, 1)
        rough = np.maximum(ev[:, 0] - noise, rough_floor * ev[:, 0])
        vp = (rough + noise / keff) / safe**2
    ok = (np.abs(cos) >= 0.3) & (tp**2 <= gate**2 * (va + vp))
    t = np.where(ok, tp * va / (va + vp), 0.0)
    return X + t[:, None] * v

for fn in ("lm-fox-extrap-w3.pkl", "lm-fox-holdout-w3.pkl"):
    o = pickle.load(open(fn, "rb"))
    d0 = evaluate(o, o["positions"])
    print(fn, "base median %.3f >2px %.3f" % (np.median(d0), np.mean(d0 > 2)))
    for mode, scale, rf in (("cons", 3, 0), ("dec", 1, 0), ("dec", 3, 0), ("dec", 3, 0.25), ("dec", 3, 0.5), ("dec", 6, 0.25)):
        for k in (12, 20, 40):
            d1 = evaluate(o, fuse2(o, k=k, scale=scale, mode=mode, rough_floor=rf))
            print(f"  {mode} scale={scale} rf={rf} k={k}: median {np.median(d1):.3f} >2px {np.mean(d1>2):.3f} p75 {np.percentile(d1,75):.2f}")
