import pickle, numpy as np, itertools
from favormap.geometry import rotvec_to_rotmat
d = pickle.load(open('/tmp/s19/poses-fox-extrap_fox-holdout.pkl', 'rb'))
def centre(T): return -T[:3, :3].T @ T[:3, 3]
for split in ['fox-extrap', 'fox-holdout']:
    for seed in ['', '-s1', '-s2']:
        srcs = ['rendered', 'mean', 'nearest']
        C = {s: np.array([centre(q['est']) for q in d[(split, seed, s)]]) for s in srcs}
        W = {s: [np.linalg.inv(q['cov'][0]) if q['cov'] is not None else np.eye(3) for q in d[(split, seed, s)]] for s in srcs}
        gt = np.array([centre(q['gt']) for q in d[(split, seed, 'rendered')]])
        line = []
        for combo in [('rendered',), ('nearest',), ('rendered', 'nearest'), ('rendered', 'mean', 'nearest'), ('rendered', 'mean')]:
            c = np.mean([C[s] for s in combo], 0)
            e = np.linalg.norm(c - gt, axis=1)
            # covariance-weighted
            cw = []
            for i in range(len(gt)):
                Wi = sum(W[s][i] for s in combo); b = sum(W[s][i] @ C[s][i] for s in combo)
                cw.append(np.linalg.solve(Wi, b))
            ew = np.linalg.norm(np.array(cw) - gt, axis=1)
            line.append(f"{'+'.join(x[0] for x in combo)} {np.median(e)*1000:.2f}/{np.median(ew)*1000:.2f}")
        print(split, seed or '-s0', ' | '.join(line))
