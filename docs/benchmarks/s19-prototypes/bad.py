import pickle, numpy as np
from favormap.geometry import project
from favormap.localize.refine import estimate_noise, refine_pose, projection_information, mahalanobis2
from harness import d, centre
from favormap.mapfile import Map
def auc(score, label):
    o = np.argsort(score); r = np.empty(len(score)); r[o] = np.arange(len(score))
    n1 = label.sum(); n0 = len(label) - n1
    return (r[label].sum() - n1 * (n1 - 1) / 2) / (n1 * n0)
rows = []
for key in ['fox-extrap', 'fox-extrap-s1', 'fox-extrap-s2']:
    m = Map.open(f"/tmp/acc15/{key}.h5")
    for q in d[key]:
        T, s, k = estimate_noise(q['pose0'], q['X'], q['kp'], q['K'], q['Xcov'], 0.5)
        Tf = refine_pose(T, q['X'], q['kp'], q['K'], s * q['Xcov'], k)
        r_est = np.linalg.norm(project(q['K'], Tf, q['X']) - q['kp'], axis=1)
        uv, info = projection_information(Tf, q['X'], q['K'], s * q['Xcov'], k)
        m2 = mahalanobis2(info, q['kp'] - uv)
        r_gt = np.linalg.norm(project(q['K'], q['gt'], q['X']) - q['kp'], axis=1)
        lstd = np.sqrt(np.trace(np.linalg.inv(info), axis1=1, axis2=2))
        bd = q['by_desc'] if q['by_desc'] is not None else np.ones(len(q['X']), bool)
        rows.append(dict(key=key, q=q, Tf=Tf, s=s, k=k, r_est=r_est, m2=m2, r_gt=r_gt, lstd=lstd, guided=~bd,
                         tl=m.track_length[q['rows']].astype(float) if 'rows' in q else None))
    m.close()
cat = lambda f: np.concatenate([r[f] for r in rows])
bad = cat('r_gt') > 2.0
print('inliers', len(bad), 'bad share', bad.mean().round(3))
for f in ['r_est', 'm2', 'lstd', 'guided']:
    print(f, 'AUC', round(auc(cat(f).astype(float), bad), 3))
# oracle removal and rule removal
for name, rule in [('oracle', lambda r: r['r_gt'] <= 2.0), ('m2<9', lambda r: r['m2'] < 9), ('m2<6', lambda r: r['m2'] < 6), ('r_est<2', lambda r: r['r_est'] < 2)]:
    out = {}
    for r in rows:
        q, keep = r['q'], rule(r)
        T = refine_pose(r['Tf'], q['X'][keep], q['kp'][keep], q['K'], r['s'] * q['Xcov'][keep], r['k']) if keep.sum() >= 6 else r['Tf']
        out.setdefault(r['key'], []).append(np.linalg.norm(centre(T) - centre(q['gt'])))
    print(name, ' '.join(f"{np.median(v)*1000:.2f}" for v in out.values()))
