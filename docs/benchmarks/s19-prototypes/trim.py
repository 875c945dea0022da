import numpy as np, sys
from favormap.localize.refine import estimate_noise, refine_pose, projection_information, mahalanobis2
from harness import d, centre
def final(q, c=None, reest=False, rounds=1, loss=1.0):
    X, kp, K, cov = q['X'], q['kp'], q['K'], q['Xcov']
    T, s, k = estimate_noise(q['pose0'], X, kp, K, cov, 0.5)
    T = refine_pose(T, X, kp, K, s * cov, k, loss_scale=loss)
    if c is None: return T
    keep = np.ones(len(X), bool)
    for _ in range(rounds):
        uv, info = projection_information(T, X, K, s * cov, k)
        m2 = mahalanobis2(info, kp - uv)
        keep = np.isfinite(m2) & (m2 < c)
        if keep.sum() < 6: return T
        if reest:
            T, s, k = estimate_noise(T, X[keep], kp[keep], K, cov[keep], k)
        T = refine_pose(T, X[keep], kp[keep], K, s * cov[keep], k, loss_scale=loss)
    return T
def show(name, **kw):
    res = {}
    for key, qs in d.items():
        res[key] = np.median([np.linalg.norm(centre(final(q, **kw)) - centre(q['gt'])) for q in qs]) * 1000
    ex = [res[k] for k in res if 'extrap' in k]; ho = [res[k] for k in res if 'holdout' in k]
    print(f"{name:26s} extrap {' '.join(f'{x:.2f}' for x in ex)} (mean {np.mean(ex):.3f})  holdout {' '.join(f'{x:.2f}' for x in ho)} (mean {np.mean(ho):.3f})", flush=True)
show('default')
for c in [4.0, 6.0, 9.0]:
    show(f'trim {c}', c=c)
    show(f'trim {c} reest', c=c, reest=True)
show('trim 6 reest x2', c=6.0, reest=True, rounds=2)
show('trim 6 x2', c=6.0, rounds=2)
ss = {key: [estimate_noise(q['pose0'], q['X'], q['kp'], q['K'], q['Xcov'], 0.5)[1] for q in qs] for key, qs in d.items()}
for key, v in ss.items(): print(key, 'landmark scale s: min/median/max', np.round([min(v), np.median(v), max(v)], 2))
def final_gated(q, c=6.0, smin=2.0):
    X, kp, K, cov = q['X'], q['kp'], q['K'], q['Xcov']
    T, s, k = estimate_noise(q['pose0'], X, kp, K, cov, 0.5)
    T = refine_pose(T, X, kp, K, s * cov, k)
    if s < smin: return T
    uv, info = projection_information(T, X, K, s * cov, k)
    m2 = mahalanobis2(info, kp - uv); keep = np.isfinite(m2) & (m2 < c)
    return refine_pose(T, X[keep], kp[keep], K, s * cov[keep], k) if keep.sum() >= 6 else T
for smin in [1.5, 2.0, 3.0, 5.0]:
    res = {key: np.median([np.linalg.norm(centre(final_gated(q, 6.0, smin)) - centre(q['gt'])) for q in qs]) * 1000 for key, qs in d.items()}
    print('gated s>=', smin, {k: round(v, 2) for k, v in res.items()})
