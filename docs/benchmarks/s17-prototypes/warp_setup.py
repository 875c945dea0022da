"""The shared setup of the warp prototypes: bench_novel_view's orbit scene and query set, SIFT,
600 landmarks, their normals (mesh and 12-nearest-landmark PCA) and the plane-induced homography."""
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



def query_pairs(query_step: int = 1, landmark_step: int = 1):
    """Every query_step-th query with every landmark_step-th of its visible, unoccluded landmarks:
    yields (kind, T, vis, uv, truth, near_f, near_o, ang): the landmarks, their projections, the
    query's own descriptors there, the nearest training frame and observation by angle, the angle."""
    for kind, T in queries[::query_step]:
        img, depth = render(scene, cam, T)
        vis = np.flatnonzero(project_inside(X, cam, T, margin_px=8))
        Xc = X[vis] @ T[:3, :3].T + T[:3, 3]
        uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
        ui = np.clip(uv.astype(int), 0, [W - 1, H - 1])
        ok = np.abs(depth[ui[:, 1], ui[:, 0]] - Xc[:, 2]) < 0.02 * Xc[:, 2] + 0.005
        vis, uv = vis[ok][::landmark_step], uv[ok][::landmark_step]
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
        yield kind, T, vis, uv, truth, near_f, near_o, ang
