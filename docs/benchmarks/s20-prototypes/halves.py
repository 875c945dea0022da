import numpy as np
from favormap.localize.refine import estimate_noise, refine_pose
from harness import d, centre
rng = np.random.default_rng(0)
for key, qs in d.items():
    cs, ratio, full = [], [], []
    for q in qs:
        X, kp, K, cov = q['X'], q['kp'], q['K'], q['Xcov']
        T, s, k = estimate_noise(q['pose0'], X, kp, K, cov, 0.5)
        Tf = refine_pose(T, X, kp, K, s * cov, k)
        ef = centre(Tf) - centre(q['gt'])
        for rep in range(5):
            p = rng.permutation(len(X)); a, b = p[: len(X) // 2], p[len(X) // 2:]
            e = [centre(refine_pose(Tf, X[i], kp[i], K, s * cov[i], k)) - centre(q['gt']) for i in (a, b)]
            cs.append(e[0] @ e[1] / (np.linalg.norm(e[0]) * np.linalg.norm(e[1])))
            # common part vs difference
            ratio.append(np.linalg.norm(e[0] - e[1]) / 2 / np.linalg.norm(ef))
        full.append(np.linalg.norm(ef))
    print(f"{key:16s} median |e_full| {np.median(full)*1000:.2f}  cos(e_half1, e_half2) median {np.median(cs):.2f}  |e1-e2|/2 / |e_full| median {np.median(ratio):.2f}")
