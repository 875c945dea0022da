import pickle, numpy as np, sys
o = pickle.load(open(sys.argv[1], "rb"))
p = o["pairs"]; lm = p["lm"]; d = p["d"]
print("landmarks", o["n"], "pairs", len(d), "median %.2f >2px %.2f" % (np.median(d), np.mean(d > 2)))
def corr(name, v):
    from scipy.stats import spearmanr
    x = v[lm]
    qs = np.quantile(x, [0, .2, .4, .6, .8, 1])
    meds = [np.median(d[(x >= qs[i]) & (x <= qs[i+1])]) for i in range(5)]
    bad = [np.mean(d[(x >= qs[i]) & (x <= qs[i+1])] > 2) for i in range(5)]
    print(f"{name:8s} rho {spearmanr(x, d)[0]:+.2f} quintile medians", " ".join(f"{m:.2f}" for m in meds), " >2px", " ".join(f"{b:.2f}" for b in bad))
for k in ("length", "angle", "mre", "maxre", "cons", "minc", "depth"):
    corr(k, o[k].astype(float))
corr("ray_ang", None) if False else None
x = p["ang"]; qs = np.quantile(x, [0, .2, .4, .6, .8, 1])
print("ray angle quintiles", np.round(qs, 1), [round(float(np.median(d[(x >= qs[i]) & (x <= qs[i+1])])), 2) for i in range(5)])
