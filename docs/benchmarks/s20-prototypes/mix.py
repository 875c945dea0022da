import numpy as np, sys
from favormap.localize.refine import estimate_noise, refine_pose, projection_information, mahalanobis2
from harness import d, centre
def default(q):
    T, s, k = estimate_noise(q['pose0'], q['X'], q['kp'], q['K'], q['Xcov'], 0.5)
    return refine_pose(T, q['X'], q['kp'], q['K'], s * q['Xcov'], k, loss_scale=1.0)
def mix(q, rounds=10, pi0=0.1, kappa0=10.0, cauchy=1e6, fix_kappa=None, start_default=True):
    X, kp, K, cov = q['X'], q['kp'], q['K'], q['Xcov']
    T, s, k = estimate_noise(q['pose0'], X, kp, K, cov, 0.5)
    if start_default:
        T = refine_pose(T, X, kp, K, s * cov, k, loss_scale=1.0)
    pi, kappa = pi0, kappa0 if fix_kappa is None else fix_kappa
    for _ in range(rounds):
        uv, info = projection_information(T, X, K, s * cov, k)
        m2 = mahalanobis2(info, kp - uv)
        ok = np.isfinite(m2)
        # 2-D Gaussian densities up to a common factor: det(C)^-1/2 exp(-m2/2); outlier C = kappa C_in
        lin = np.log(1 - pi) - 0.5 * m2
        lout = np.log(pi) - np.log(kappa) - 0.5 * m2 / kappa
        resp = 1 / (1 + np.exp(np.clip(lout - lin, -50, 50)))
        resp[~ok] = 0
        pi = float(np.clip(np.mean(1 - resp[ok]), 1e-3, 0.5))
        if fix_kappa is None:
            kappa = float(np.clip(np.sum((1 - resp[ok]) * m2[ok]) / (2 * max(np.sum(1 - resp[ok]), 1e-9)), 2.0, 1e4))
        vf = 1 / (resp + (1 - resp) / kappa)
        T = refine_pose(T, X, kp, K, s * cov, k, loss_scale=cauchy, variance_factor=vf)
    return T
def show(name, fn):
    res = {key: np.median([np.linalg.norm(centre(fn(q)) - centre(q['gt'])) for q in qs]) * 1000 for key, qs in d.items()}
    ex = [res[k] for k in res if 'extrap' in k]; ho = [res[k] for k in res if 'holdout' in k]
    print(f"{name:34s} extrap {' '.join(f'{x:.2f}' for x in ex)} (mean {np.mean(ex):.3f})  holdout {' '.join(f'{x:.2f}' for x in ho)} (mean {np.mean(ho):.3f})", flush=True)
if __name__ == '__main__':
    show('default', default)
    show('mix', mix)
    show('mix cauchy3', lambda q: mix(q, cauchy=3.0))
    show('mix kappa25 fixed', lambda q: mix(q, fix_kappa=25.0))
    show('mix kappa100 fixed', lambda q: mix(q, fix_kappa=100.0))
    show('mix from estimate_noise', lambda q: mix(q, start_default=False))
