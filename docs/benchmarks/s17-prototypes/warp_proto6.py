"""Prototype: does warping the nearest training view by the landmark's local plane predict the
query's SIFT descriptor better than the nearest view / mean? (bench_novel_view's orbit scene)"""
import sys, time, tempfile
from pathlib import Path
import numpy as np, cv2
sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tools"))
import bench_novel_view as bnv
from favormap import features, geometry
from favormap.build import BuildConfig, extract_sequence, select_landmarks, track_frames, training_rays, triangulate_tracks
from favormap.geometry import camera_centers
from favormap.ops.spatial import project_inside
from favormap.synthetic import camera_path, make_camera, make_room, render, write_sequence

W, H = 640, 480
scene = make_room(0); cam = make_camera(W, H)
path = camera_path(70, step=0.05, seed=0)
train_idx = list(range(20, 50))
queries = bnv.query_poses(path, train_idx, scene)
cfg = BuildConfig(extractor="sift", max_keypoints=2048, max_side=0, max_landmarks=600)
ex = features.create("sift", max_keypoints=2048)
t0 = time.time()
train_imgs = [render(scene, cam, path[i])[0] for i in train_idx]
with tempfile.TemporaryDirectory() as tmp:
    seq = write_sequence(Path(tmp) / "room", poses=[path[i] for i in train_idx], width=W, height=H, scene=scene)
    ff = extract_sequence(seq, ex, 0)
lms = select_landmarks(triangulate_tracks(track_frames(ff, cfg), ff, cfg), 600)
rays = training_rays(lms, ff, ex, 7, box_factor=1.0)
X = lms.positions; L = len(X)
P = rays.ray_dirs.shape[1]
mean_desc = np.zeros((L, 128)); np.add.at(mean_desc, rays.obs_landmark, rays.targets.mean(1))
mean_desc /= np.linalg.norm(mean_desc, axis=1, keepdims=True)
ct = rays.targets[:, P // 2]
print("landmarks", L, "prep", time.time() - t0)
Tw = ff.cam_from_world
C = camera_centers(Tw)
tr = lms.tracks
K = cam.K
# true normals: raycast from each landmark's first observing camera
import open3d as o3d
rc = scene.raycaster
first_frame = tr.frame_idx[tr.offsets[:-1]]
o = C[first_frame]; d = X - o
rr = rc.cast_rays(o3d.core.Tensor(np.hstack([o, d / np.linalg.norm(d, axis=1, keepdims=True)]).astype(np.float32)))
n_true = rr["primitive_normals"].numpy().astype(np.float64)
n_true *= -np.sign(np.sum(n_true * d, 1))[:, None]  # facing the camera
# estimated normals: PCA of the 12 nearest landmarks
from scipy.spatial import cKDTree
_, nn = cKDTree(X).query(X, k=12)
n_est = np.zeros_like(X)
for j in range(L):
    Y = X[nn[j]] - X[nn[j]].mean(0)
    n_est[j] = np.linalg.svd(Y)[2][-1]
n_est *= -np.sign(np.sum(n_est * d, 1))[:, None]
print("normal est err deg median", np.median(np.degrees(np.arccos(np.clip(np.abs(np.sum(n_est*n_true,1)),0,1)))))

def homography(Tr, Tq, Xp, n):
    Rr, tr_ = Tr[:3, :3], Tr[:3, 3]
    Rq, tq = Tq[:3, :3], Tq[:3, 3]
    Rrel = Rq @ Rr.T; trel = tq - Rrel @ tr_
    nr = Rr @ n; Yr = Rr @ Xp + tr_; dr = nr @ Yr
    return K @ (Rrel + np.outer(trel, nr) / dr) @ np.linalg.inv(K)

res = {k: [] for k in ["angle", "nearest", "mean", "warp_true", "warp_est", "mosaic"]}
TIMES = []
exm = None
DET = cv2.SIFT_create(nfeatures=0, contrastThreshold=0.02)
t0 = time.time()
for kind, T in queries[::2]:
    img, depth = render(scene, cam, T)
    vis = np.flatnonzero(project_inside(X, cam, T, margin_px=8))
    Xc = X[vis] @ T[:3, :3].T + T[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    ui = np.clip(uv.astype(int), 0, [W - 1, H - 1])
    ok = np.abs(depth[ui[:, 1], ui[:, 0]] - Xc[:, 2]) < 0.02 * Xc[:, 2] + 0.005
    vis, uv = vis[ok][::4], uv[ok][::4]
    truth = ex.sample(ex.extract(img), uv)
    c = camera_centers(T)
    # nearest training frame per landmark (by angle at the landmark)
    near_f = np.zeros(len(vis), int); near_o = np.zeros(len(vis), int); ang = np.zeros(len(vis))
    for k, j in enumerate(vis):
        s, e = tr.offsets[j], tr.offsets[j + 1]
        fr = tr.frame_idx[s:e]
        u = (c - X[j]); u /= np.linalg.norm(u)
        v = C[fr] - X[j]; v /= np.linalg.norm(v, axis=1, keepdims=True)
        a = np.degrees(np.arccos(np.clip(v @ u, -1, 1)))
        m = np.argmin(a); near_f[k] = fr[m]; near_o[k] = s + m; ang[k] = a[m]
    # rays obs index == track obs index (rays sorted by landmark, same order as tracks)
    res["angle"].append(ang); res["nearest"].append(np.sum(ct[near_o] * truth, 1))
    res["mean"].append(np.sum(mean_desc[vis] * truth, 1))
    t1 = time.perf_counter()
    tiles, tile_lm = [], []
    for k, j in enumerate(vis):
        c0 = np.floor(uv[k]) - 64
        Tr_ = np.array([[1, 0, -c0[0]], [0, 1, -c0[1]], [0, 0, 1.0]])
        for oi in range(tr.offsets[j], tr.offsets[j + 1]):
            f = tr.frame_idx[oi]
            Hm = homography(Tw[f], T, X[j], n_est[j])
            tiles.append(cv2.warpPerspective(train_imgs[f], Tr_ @ Hm, (128, 128), flags=cv2.INTER_LINEAR))
            tile_lm.append((k, uv[k] - c0))
    n = len(tiles); cols = 32; rows = (n + cols - 1) // cols
    mos = np.zeros((rows * 128, cols * 128, 3), np.uint8)
    pts = np.zeros((n, 2), np.float32)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols); mos[r*128:(r+1)*128, c*128:(c+1)*128] = t
        pts[i] = tile_lm[i][1] + [c * 128, r * 128]
    t2 = time.perf_counter()
    gray = cv2.cvtColor(mos, cv2.COLOR_RGB2GRAY)
    kps = DET.detect(gray, None)
    kxy = cv2.KeyPoint_convert(kps).reshape(-1, 2) + 0.5 if len(kps) else np.zeros((0, 2), np.float32)
    from scipy.spatial import cKDTree
    from favormap.features.sift import octave_of_size
    size = np.full(n, ex.size, np.float32); angle = np.zeros(n, np.float32); octv = np.full(n, int(octave_of_size(ex.size)), np.int64)
    if len(kxy):
        dd, nn = cKDTree(kxy).query(pts, k=1)
        near = dd <= ex.support_px
        size[near] = [kps[i].size for i in nn[near]]; angle[near] = [kps[i].angle for i in nn[near]]; octv[near] = [kps[i].octave for i in nn[near]]
    class S: pass
    S.gray = gray
    dsc = ex._describe(S, pts, size, angle, octv)
    t3 = time.perf_counter()
    TIMES.append((n, t2 - t1, t3 - t2))
    acc = np.zeros_like(truth)
    np.add.at(acc, [t[0] for t in tile_lm], dsc)
    acc /= np.linalg.norm(acc, axis=1, keepdims=True)
    res["mosaic"].append(np.sum(acc * truth, 1))
    print(kind, len(vis), f"{time.time()-t0:.0f}s", flush=True)
A = np.concatenate(res["angle"])
print("bins", bnv.BINS)
for k in ["nearest", "mean", "mosaic"]:
    print(f"{k:12s}", " ".join(f"{x:.4f}" for x in bnv.binned(np.concatenate(res[k]), A)))
print("pairs", len(A), [int(((A>=lo)&(A<hi)).sum()) for lo,hi in bnv.BINS])

n = sum(t[0] for t in TIMES); print(f"tiles {n}: warp+mosaic {sum(t[1] for t in TIMES):.1f}s, detect+describe {sum(t[2] for t in TIMES):.1f}s, {1000*sum(t[1]+t[2] for t in TIMES)/n:.2f} ms per tile")
