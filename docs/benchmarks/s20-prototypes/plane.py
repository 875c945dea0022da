import pickle, sys, numpy as np
sys.path.insert(0, "/work/main")
from favormap.localize.refine import position_covariances, reprojection_pixel_sigma
from favormap.geometry import project
from scipy.spatial import cKDTree

def evaluate(o, X):
    p = o["pairs"]; d = np.empty(len(p["q"]))
    for i in np.unique(p["q"]):
        s = p["q"] == i
        uv = project(o["qK"][i], o["qT"][i], X[p["lm"][s]])
        d[s] = np.linalg.norm(uv - p["xy"][s], axis=1)
    return d

def spread_deg(o):
    # angle spanned: max triangulation angle stored as o['angle']
    return o["angle"]

def fuse(o, k=12, gate=3.0, scale=1.0, min_cos=0.3, weighted=True):
    X = o["positions"]; v = o["view_dir"]; n = o["n"]
    sig = reprojection_pixel_sigma(o["mre"], o["length"])
    sig = np.maximum(sig, 0.2) * scale
    f = float(np.median(o["mK"][:, 0, 0]))
    across = o["depth"] * sig / (f * np.sqrt(o["length"]))
    along = across / np.sin(np.radians(np.clip(o["angle"], 0.5, 90)))
    tree = cKDTree(X)
    _, nb = tree.query(X, k + 1)
    nb = nb[:, 1:]
    P = X[nb]  # (n,k,3)
    w = 1.0 / along[nb] ** 2 if weighted else np.ones(nb.shape)
    w = w / w.sum(1, keepdims=True)
    c = (w[..., None] * P).sum(1)
    Q = P - c[:, None]
    C = np.einsum("nk,nki,nkj->nij", w, Q, Q)
    evals, evecs = np.linalg.eigh(C)
    nrm = evecs[:, :, 0]
    sp2 = evals[:, 0]  # weighted plane residual variance
    nv = np.einsum("ni,ni->n", nrm, v)
    t_star = np.einsum("ni,ni->n", nrm, c - X) / np.where(np.abs(nv) < 1e-6, 1e-6, nv)
    var_t = (sp2 + (along[nb] ** 2 * w).sum(1) / k) / np.maximum(nv**2, 1e-12)
    ok = (np.abs(nv) >= min_cos) & (t_star**2 <= gate**2 * (along**2 + var_t))
    t = np.where(ok, t_star * along**2 / (along**2 + var_t), 0.0)
    return X + t[:, None] * v, ok, t

for fn in sys.argv[1:]:
    o = pickle.load(open(fn, "rb"))
    d0 = evaluate(o, o["positions"])
    print(fn, "base median %.3f >2px %.3f p90 %.2f" % (np.median(d0), np.mean(d0 > 2), np.percentile(d0, 90)))
    for k in (8, 12, 20):
        for gate in (2.0, 3.0, 5.0):
            for scale in (1.0, 3.0):
                X1, ok, t = fuse(o, k, gate, scale)
                d1 = evaluate(o, X1)
                print(f"  k={k} gate={gate} scale={scale}: moved {ok.mean():.2f} median {np.median(d1):.3f} >2px {np.mean(d1>2):.3f} p90 {np.percentile(d1,90):.2f}")

def iterate(o, iters, **kw):
    o2 = dict(o); X = o["positions"]
    for _ in range(iters):
        o2["positions"] = X
        X, ok, t = fuse(o2, **kw)
    return X
