"""Prototype: voxel grids trained with warped-mean targets on the virtual prior rays.

    python warp_train.py V NOBS [VARIANTS]   # V virtual directions per landmark, NOBS views each
"""
import sys, time, dataclasses
from pathlib import Path
import numpy as np, cv2, torch
from warp_setup import *  # noqa: F403 (scene, landmarks, rays, normals, homography)
from favormap.voxels import VoxelConfig, train_voxels, render_from_camera
import favormap.voxels.train as vt
from favormap.geometry import look_at
from favormap.synthetic.scene import UP
V, NOBS = int(sys.argv[1]), int(sys.argv[2])
orig_bank = vt._prior_bank
grays = [ff.features[f].dense.gray for f in range(len(ff.features))]

_CACHE = {}
def warped_bank(data, cfg, centers, sizes, targets, mean_desc, counts, first, gen):
    o, d, t = orig_bank(data, cfg, centers, sizes, targets, mean_desc, counts, first, gen)
    if 'x' in _CACHE: return o, d, _CACHE['x']
    t0 = time.time()
    cen = (o - 0.5) * sizes[:, None, None] + centers[:, None, :]  # (L, V, 3) virtual camera centres
    newt = t.clone(); done = 0
    for j in range(L):
        s, e = tr.offsets[j], tr.offsets[j + 1]
        for vi in range(cen.shape[1]):
            c = cen[j, vi].double().numpy()
            Tq = look_at(c, X[j], up=UP)
            # nearest NOBS observations by angle
            u = c - X[j]; u /= np.linalg.norm(u)
            vv = C[tr.frame_idx[s:e]] - X[j]; vv /= np.linalg.norm(vv, axis=1, keepdims=True)
            order = np.argsort(-(vv @ u))[:NOBS]
            acc = np.zeros(128)
            uvq = K @ (Tq[:3, :3] @ X[j] + Tq[:3, 3]); uvq = uvq[:2] / uvq[2]
            for oi in s + order:
                f = tr.frame_idx[oi]
                Hm = homography(Tw[f], Tq, X[j], n_est[j])
                c0 = np.floor(uvq) - 64
                Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
                patch = cv2.warpPerspective(train_imgs[f], Tr_ @ Hm, (128, 128), flags=cv2.INTER_LINEAR)
                acc += ex.sample(ex.extract(patch), (uvq - c0)[None])[0]
            newt[j, vi] = torch.as_tensor(acc / max(np.linalg.norm(acc), 1e-9), dtype=newt.dtype)
            done += 1
    print(f"warped targets {done} in {time.time()-t0:.0f}s; cos to old {float((newt*t).sum(-1).mean()):.3f}", flush=True)
    _CACHE['x'] = newt
    return o, d, newt

def evaluate_grids(grids, cfg, sizes):
    centers = torch.as_tensor(X, dtype=torch.float32); sz = torch.as_tensor(sizes, dtype=torch.float32)
    sims, angs = [], []
    for q in QS:
        v = torch.as_tensor(q["vis"]).long()
        r = render_from_camera(grids.descriptors[v], grids.density[v], centers[v], sz[v], torch.as_tensor(q["center"]).float(), cfg.samples).numpy()
        sims.append(np.sum(r * q["truth"], 1)); angs.append(q["angle"])
    return np.concatenate(sims), np.concatenate(angs)

QS = []
for kind, T in queries:
    img, depth = render(scene, cam, T)
    vis = np.flatnonzero(project_inside(X, cam, T, margin_px=8))
    Xc = X[vis] @ T[:3, :3].T + T[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    ui = np.clip(uv.astype(int), 0, [W - 1, H - 1])
    ok = np.abs(depth[ui[:, 1], ui[:, 0]] - Xc[:, 2]) < 0.02 * Xc[:, 2] + 0.005
    vis, uv = vis[ok], uv[ok]
    truth = ex.sample(ex.extract(img), uv)
    c = camera_centers(T)
    ang = np.zeros(len(vis)); near_o = np.zeros(len(vis), int)
    for k, j in enumerate(vis):
        s, e = tr.offsets[j], tr.offsets[j + 1]
        u = (c - X[j]); u /= np.linalg.norm(u)
        v = C[tr.frame_idx[s:e]] - X[j]; v /= np.linalg.norm(v, axis=1, keepdims=True)
        a = np.degrees(np.arccos(np.clip(v @ u, -1, 1))); ang[k] = a.min(); near_o[k] = s + np.argmin(a)
    QS.append(dict(vis=vis, truth=truth, center=c, angle=ang, near_o=near_o))
A = np.concatenate([q["angle"] for q in QS])
print("nearest ", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate([np.sum(ct[q['near_o']]*q['truth'],1) for q in QS]), A)))
print("mean    ", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate([np.sum(mean_desc[q['vis']]*q['truth'],1) for q in QS]), A)))
# variants: NAME[-pwW], NAME "warped" (warped-track targets) or anything else (the default targets,
# e.g. "control" / "default64"), W the prior rays' weight (default 1)
VARIANTS = (sys.argv[3] if len(sys.argv) > 3 else "control,warped").split(",")
for name in VARIANTS:
    warped = name.startswith("warped")
    pw = float(name.split("-pw")[1]) if "-pw" in name else 1.0
    cfg = VoxelConfig(prior_bank=V, prior_mean_deg=10.0, prior_weight=pw)
    vt._prior_bank = warped_bank if warped else orig_bank
    r2 = dataclasses.replace(rays, sizes=rays.sizes * cfg.box_factor)
    t0 = time.time(); g = train_voxels(r2, cfg); tt = time.time() - t0
    sims, a = evaluate_grids(g, cfg, r2.sizes)
    print(f"{name:8s}", " ".join(f"{x:.4f}" for x in bnv.binned(sims, a)), f"train {tt:.0f}s", flush=True)
print("pairs", [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])
