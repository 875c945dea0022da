"""Unit tests of the geometric and rendering core: triangulation, stencils, rendering, training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from favormap.geometry import camera_centers, look_at
from favormap.tracking import Tracks
from favormap.triangulation import TriangulationConfig, triangulate
from favormap.voxels.render import box_intersections, render_from_camera, trilinear_stencil


def _scene(n_points=200, n_cams=8, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1, -1, 4], [1, 1, 6], size=(n_points, 3))
    T = np.stack([look_at([x, 0.2 * np.sin(x), 0], [0, 0, 5], up=(0, -1, 0)) for x in np.linspace(-1, 1, n_cams)])
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    return X, T, np.repeat(K[None], n_cams, 0), rng


def _observe(X, T, K, rng, noise_px):
    fi, tid, xy = [], [], []
    for j, x in enumerate(X):
        for i in range(len(T)):
            p = K[i] @ (T[i, :3, :3] @ x + T[i, :3, 3])
            fi.append(i)
            tid.append(j)
            xy.append(p[:2] / p[2] + rng.normal(0, noise_px, 2))
    n = len(fi)
    return Tracks.from_obs(np.array(fi), np.arange(n), np.array(xy), np.array(tid))


def test_triangulation_is_accurate_and_robust_to_outliers():
    X, T, K, rng = _scene()
    tracks = _observe(X, T, K, rng, noise_px=0.5)
    # corrupt one observation in every 4th track by 40 px
    bad = tracks.offsets[:-1][::4] + 3
    tracks.xy[bad] += 40.0
    lms = triangulate(tracks, T, K, TriangulationConfig(max_reproj_px=3.0, min_track=5))
    # every track survives; exactly the corrupted observations are dropped
    assert len(lms) == len(X)
    assert len(lms.reproj_errors) == len(tracks.frame_idx) - len(bad)
    assert np.max(lms.reproj_errors) <= 3.0 and np.median(lms.reproj_errors) < 1.0
    err = np.linalg.norm(lms.positions - X, axis=1)  # track j <-> X[j]
    assert np.median(err) < 0.01  # 1 cm at 5 m with 0.5 px noise


def test_triangulation_in_blocks_equals_one_block(monkeypatch):
    """Tracks are solved in blocks of observations (bounded memory): the result is the same."""
    import favormap.triangulation as tri

    X, T, K, rng = _scene()
    tracks = _observe(X, T, K, rng, noise_px=0.5)
    tracks.xy[tracks.offsets[:-1][::4] + 3] += 40.0
    cfg = TriangulationConfig(max_reproj_px=3.0, min_track=5)
    whole = triangulate(tracks, T, K, cfg)
    monkeypatch.setattr(tri, "BLOCK_OBSERVATIONS", 37)  # many blocks, cut inside tracks
    blocks = triangulate(tracks, T, K, cfg)
    assert np.array_equal(whole.positions, blocks.positions) and np.array_equal(whole.angles_deg, blocks.angles_deg)
    assert np.array_equal(whole.reproj_errors, blocks.reproj_errors)
    for k in ("frame_idx", "keypoint_idx", "xy", "offsets"):
        assert np.array_equal(getattr(whole.tracks, k), getattr(blocks.tracks, k)), k


def test_triangulation_rejects_points_behind_and_tiny_angles():
    X, T, K, rng = _scene(n_points=20)
    tracks = _observe(X, T, K, rng, noise_px=0.0)
    # a degenerate configuration: every camera at the same centre (no parallax)
    T2 = T.copy()
    for i in range(len(T2)):
        T2[i, :3, 3] = -T2[i, :3, :3] @ np.zeros(3)
    lms = triangulate(tracks, T2, K, TriangulationConfig(min_angle_deg=1.0))
    assert len(lms) == 0


def test_trilinear_stencil_interpolates_linear_functions_exactly():
    R = 3
    pts = torch.rand(500, 3)
    st = trilinear_stencil(pts, R)
    nodes = torch.stack(torch.meshgrid(*[torch.arange(R, dtype=torch.float32)] * 3, indexing="ij"), -1).reshape(
        -1, 3
    ) / (R - 1)
    assert torch.allclose(st.sum(-1), torch.ones(500))
    assert torch.allclose(st @ nodes, pts, atol=1e-6)


def test_box_intersections():
    o = torch.tensor([[-1.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-1.0, 2.0, 0.5]])
    d = torch.tensor([[1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    tn, tf, hit = box_intersections(o, d)
    assert hit.tolist() == [True, True, False]
    assert torch.allclose(tn[:2], torch.tensor([1.0, 0.0])) and torch.allclose(tf[:2], torch.tensor([2.0, 0.5]))


def test_rendering_a_constant_grid_returns_the_constant():
    L, R, C = 5, 3, 8
    d = torch.nn.functional.normalize(torch.randn(L, C), dim=-1)
    desc = d[:, None, :].expand(L, R**3, C).contiguous()
    dens = torch.full((L, R**3), 3.0)
    centers = torch.randn(L, 3) + torch.tensor([0, 0, 5.0])
    sizes = torch.full((L,), 0.1)
    out = render_from_camera(desc, dens, centers, sizes, torch.zeros(3), 12)
    assert torch.allclose(out, d, atol=1e-5)
    # unnormalised: scaled by the accumulated opacity (< 1, > 0)
    raw = render_from_camera(desc, dens, centers, sizes, torch.zeros(3), 12, normalize=False)
    scale = (raw * d).sum(-1)
    assert torch.all(scale > 0.5) and torch.all(scale < 1.0)


def test_rendering_depends_on_the_viewing_direction():
    """Nodes in front of the centre (seen from +x) dominate what a camera on the +x side renders."""
    R, C = 3, 4
    desc = torch.zeros(1, R, R, R, C)
    desc[0, 2, :, :, 0] = 1.0  # x = +side nodes: channel 0
    desc[0, 0, :, :, 1] = 1.0  # x = -side nodes: channel 1
    desc[0, 1, :, :, 2] = 1.0
    dens = torch.full((1, R**3), 20.0)
    c, s = torch.zeros(1, 3), torch.ones(1)
    plus = render_from_camera(desc.view(1, -1, C), dens, c, s, torch.tensor([5.0, 0, 0]), 16)
    minus = render_from_camera(desc.view(1, -1, C), dens, c, s, torch.tensor([-5.0, 0, 0]), 16)
    assert plus[0, 0] > plus[0, 1] and minus[0, 1] > minus[0, 0]


def _patch_rays(L=6, C=8, S=5):
    """TrainingRays of L landmarks seen by 6 cameras: S x S patch rays whose targets are noisy
    copies of one unit descriptor per landmark."""
    from favormap.features import patch_offsets
    from favormap.voxels import TrainingRays

    rng = np.random.default_rng(0)
    X, T, K, _ = _scene(n_points=L, n_cams=6)
    offs = patch_offsets(S)
    obs_lm, origins, dirs, targets = [], [], [], []
    base = rng.normal(size=(L, C))
    for j in range(L):
        for i in range(len(T)):
            p = K[i] @ (T[i, :3, :3] @ X[j] + T[i, :3, 3])
            uv = p[:2] / p[2] + offs
            d_cam = np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K[i]).T
            dirs.append(d_cam @ T[i, :3, :3])
            origins.append(camera_centers(T[i]))
            obs_lm.append(j)
            t = base[j] + 0.1 * rng.normal(size=(len(offs), C))
            targets.append(t / np.linalg.norm(t, axis=1, keepdims=True))
    dist = np.linalg.norm(X[:, None] - camera_centers(T)[None], axis=2).min(1)
    return TrainingRays(
        X,
        S * dist / 500.0,
        np.array(obs_lm),
        np.array(origins),
        np.array(dirs, np.float32),
        np.array(targets, np.float32),
    )


@pytest.mark.parametrize("solver", ["lstsq", "adam"])
def test_voxel_training_fits_patches(solver):
    """End to end on synthetic rays: grids trained jointly reproduce per-landmark targets."""
    from favormap.voxels import VoxelConfig, train_voxels

    data = _patch_rays(L=6, C=8, S=5)
    cfg = VoxelConfig(resolution=3, patch_size=5, iterations=150, rays_per_landmark=32, solver=solver)
    grids = train_voxels(data, cfg)
    assert grids.descriptors.shape == (6, 27, 8)
    assert np.all(grids.cosine > 0.9) and np.all(grids.psnr > 20)
    if solver == "adam":
        assert grids.history[-1][1] < grids.history[0][1]  # loss went down


def _tv_by_slices(x: torch.Tensor, R: int) -> torch.Tensor:
    """The total-variation term of a stack of grids (L, R^3, C) by its definition: the mean squared
    difference of neighbouring nodes along each axis, summed over the axes."""
    g = x.view(x.shape[0], R, R, R, -1)
    return (
        ((g[:, 1:] - g[:, :-1]) ** 2).mean()
        + ((g[:, :, 1:] - g[:, :, :-1]) ** 2).mean()
        + ((g[:, :, :, 1:] - g[:, :, :, :-1]) ** 2).mean()
    )


def test_closed_form_tv_gradient_equals_autograd_through_the_tv_term():
    """Training adds the total-variation term's gradient in closed form (train._TVGradient): the same
    value and gradients as autograd through the term's definition, on grids of random descriptors and
    densities."""
    from favormap.voxels.train import _TVGradient

    torch.manual_seed(0)
    L, C, R, w = 7, 16, 3, 0.37
    desc = torch.randn(L, R**3, C, requires_grad=True)
    dens = torch.randn(L, R**3, requires_grad=True)
    tv = w * (_tv_by_slices(desc, R) + _tv_by_slices(dens[..., None], R))
    tv.backward()
    g_desc, g_dens = desc.grad.clone(), dens.grad.clone()
    desc.grad.zero_()
    dens.grad.zero_()
    value = _TVGradient(R, L, C, "cpu").add_to(desc, dens, w)
    assert value == pytest.approx(float(tv.detach()), rel=1e-5)
    torch.testing.assert_close(desc.grad, g_desc, rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(dens.grad, g_dens, rtol=1e-5, atol=1e-8)
    assert g_desc.abs().max() > 1e-4  # not trivially zero


@pytest.mark.parametrize("solver", ["adam", "lstsq"])
def test_training_several_batches_as_one_task_gives_the_same_grids(solver):
    """train_batches: an executor that trains consecutive batches together (a local GPU does, 16 at a
    time) gets the grids of training them one by one: each batch draws its own random rays, and the
    landmarks are independent. Batches of 3 landmarks: 5, 5 and 4 of them, trained as one task."""
    from favormap.build import train_batches
    from favormap.executor import LocalExecutor
    from favormap.voxels import VoxelConfig, train_voxels

    class Grouping(LocalExecutor):
        def train_group(self):
            return 16

    data = _patch_rays(L=14, C=8, S=5)
    cfg = VoxelConfig(resolution=3, patch_size=5, iterations=30, rays_per_landmark=16, solver=solver, seed=3)
    one_by_one = train_batches(data, cfg, 5, LocalExecutor("cpu", workers=1))
    together = train_batches(data, cfg, 5, Grouping("cpu", workers=1))
    np.testing.assert_allclose(together.descriptors.numpy(), one_by_one.descriptors.numpy(), atol=2e-5)
    np.testing.assert_allclose(together.density.numpy(), one_by_one.density.numpy(), atol=2e-4, rtol=1e-5)
    np.testing.assert_allclose(together.psnr, one_by_one.psnr, atol=1e-3)
    # not trivially: one generator for all 14 landmarks (what train_voxels alone does) draws other rays
    single = train_voxels(data, cfg)
    assert np.abs(single.descriptors.numpy() - one_by_one.descriptors.numpy()).max() > 1e-3


def test_adam_from_the_closed_form_starts_where_the_mean_init_does_not_reach_quickly():
    """init="lstsq": Adam starts from the closed-form descriptors, so its first loss is already below
    the mean initialisation's, and a short run ends at least as low."""
    from favormap.voxels import VoxelConfig, train_voxels

    data = _patch_rays(L=6, C=8, S=5)
    runs = {
        init: train_voxels(data, VoxelConfig(resolution=3, patch_size=5, iterations=30, init=init, solver="adam"))
        for init in ("mean", "lstsq")
    }
    assert runs["lstsq"].history[0][1] < runs["mean"].history[0][1]
    assert runs["lstsq"].history[-1][1] <= runs["mean"].history[-1][1]
    assert np.all(runs["lstsq"].cosine > 0.9)


def test_lstsq_solver_is_the_regularised_least_squares_fit():
    """The closed-form solver's descriptors equal a direct least-squares solve of the stacked,
    weighted system: every patch ray's composite stencil (fixed uniform density) against its
    target, the ridge towards the mean descriptor and the smoothness rows of neighbouring nodes."""
    import torch

    from favormap.voxels import VoxelConfig, train_voxels
    from favormap.voxels.render import composite, ray_stencils

    S, R = 5, 3
    data = _patch_rays(L=3, C=4, S=S)
    cfg = VoxelConfig(
        resolution=R, patch_size=S, prior_rays=0, lstsq_ridge=0.05, lstsq_tv=0.2, centre_rays=0.5, solver="lstsq"
    )
    grids = train_voxels(data, cfg)
    got = grids.descriptors.double().numpy()
    # its training curve is one point, the solution's: PSNR of the landmarks' mean squared error
    ((it, loss, psnr),) = grids.history
    mse = 4.0 / 10 ** (grids.psnr.astype(np.float64) / 10)
    assert it == cfg.iterations - 1 and np.isclose(psnr, 10 * np.log10(4.0 / mse.mean()), atol=1e-4)
    assert np.isclose(loss, np.mean(4 * mse + 1 - grids.cosine), rtol=1e-5) and loss > 0
    P = S * S
    pix_w = np.full(P, 0.5 / P)
    pix_w[P // 2] += 0.5
    idx = np.arange(R**3).reshape(R, R, R)
    pairs = [
        (a, b)
        for ax in range(3)
        for a, b in zip(np.take(idx, range(R - 1), ax).ravel(), np.take(idx, range(1, R), ax).ravel())
    ]
    for j in range(3):
        obs = np.flatnonzero(data.obs_landmark == j)
        o = (data.obs_origin[obs] - data.centers[j]) / data.sizes[j] + 0.5
        st, delta, hit = ray_stencils(
            torch.tensor(o, dtype=torch.float64)[:, None].expand(-1, P, -1),
            torch.tensor(data.ray_dirs[obs], dtype=torch.float64),
            R,
            cfg.samples,
        )
        dens = torch.full((len(obs), R**3), float(np.log(np.expm1(cfg.density_init))), dtype=torch.float64)
        a = composite(st, delta, dens, hit)[0].numpy().reshape(-1, R**3)
        w = np.sqrt(np.tile(pix_w, len(obs)) / len(obs))[:, None]
        t = data.targets[obs].reshape(-1, data.targets.shape[-1]).astype(np.float64)
        mean = data.targets[obs].mean(1).sum(0)
        mean /= np.linalg.norm(mean)
        D = np.zeros((len(pairs), R**3))
        for k, (u, v) in enumerate(pairs):
            D[k, u], D[k, v] = 1.0, -1.0
        rows = np.vstack([w * a, np.sqrt(cfg.lstsq_ridge) * np.eye(R**3), np.sqrt(cfg.lstsq_tv) * D])
        rhs = np.vstack(
            [w * t, np.sqrt(cfg.lstsq_ridge) * np.tile(mean, (R**3, 1)), np.zeros((len(pairs), t.shape[1]))]
        )
        want = np.linalg.lstsq(rows, rhs, rcond=None)[0]
        assert np.allclose(got[j], want, atol=2e-4), np.abs(got[j] - want).max()


def test_uniform_density_compositing_equals_the_general_one():
    """render.composite_uniform (the closed form's fixed densities) gives composite's stencils and
    opacities of ray_stencils, for rays through the box from outside, from inside and missing it."""
    from favormap.voxels.render import composite, composite_uniform, ray_stencils

    torch.manual_seed(1)
    R, N, B, K = 3, 12, 5, 40
    origins = torch.rand(B, K, 3) * 4 - 1.5  # local frame: the box is [0, 1]^3
    dirs = torch.nn.functional.normalize(0.5 - origins + 0.6 * torch.randn(B, K, 3), dim=-1)
    for density in (0.5, 20.0):
        raw = torch.full((B, R**3), float(np.log(np.expm1(density))))
        st, delta, hit = ray_stencils(origins, dirs, R, N)
        want_a, want_op = composite(st, delta, raw, hit)
        a, op = composite_uniform(origins, dirs, R, N, float(torch.nn.functional.softplus(raw[0, 0])))
        torch.testing.assert_close(a, want_a, atol=2e-6, rtol=1e-5)
        torch.testing.assert_close(op, want_op, atol=2e-6, rtol=1e-5)
        assert (op == 0).any() and (op > 0.3).any()  # some rays miss the box, others cross it


def test_closed_form_fit_figures_are_those_of_rendering_the_training_rays_again():
    """The closed form reports each landmark's PSNR and cosine from the stencils its fit made
    (train._fit_quality): the figures of :func:`evaluate`, which traces every training ray again
    through the solved grids, over several ray chunks (max_batch_rays)."""
    from favormap.voxels import VoxelConfig, train_voxels
    from favormap.voxels.train import evaluate

    data = _patch_rays(L=9, C=8, S=5)
    cfg = VoxelConfig(resolution=3, patch_size=5, solver="lstsq", density_init=20.0, max_batch_rays=4 * 25)
    grids = train_voxels(data, cfg)
    psnr, cosine = evaluate(data, grids.descriptors, grids.density, cfg)
    np.testing.assert_allclose(grids.psnr, psnr, atol=1e-3)
    np.testing.assert_allclose(grids.cosine, cosine, atol=1e-5)
    assert np.ptp(psnr) > 0.1 and 0.5 < cosine.min() < cosine.max() < 1.0  # landmarks differ: not a constant
    # beyond the memory bound for the kept stencils, the same figures by tracing the rays again
    import favormap.voxels.train as train

    bound, train._KEEP_STENCIL_BYTES = train._KEEP_STENCIL_BYTES, 0
    try:
        traced = train_voxels(data, cfg)
    finally:
        train._KEEP_STENCIL_BYTES = bound
    np.testing.assert_allclose(traced.psnr, grids.psnr, atol=1e-3)
    np.testing.assert_allclose(traced.descriptors.numpy(), grids.descriptors.numpy(), atol=1e-6)


def test_quaternions_match_scipy_including_half_turns():
    """The NumPy quaternion conversions (the localization path imports no scipy) agree with scipy's
    Rotation on random rotations and on the half turns where the trace-based formula breaks down."""
    from scipy.spatial.transform import Rotation

    from favormap.geometry import quat_to_rotmat, rotmat_to_quat

    rots = Rotation.concatenate(
        [
            Rotation.random(500, random_state=3),
            Rotation.from_rotvec(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0], [0, 0, 0.0]])),
        ]
    )
    mats = rots.as_matrix()
    for R in mats:
        q = rotmat_to_quat(R)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        assert np.allclose(quat_to_rotmat(q), R, atol=1e-12)
        ref = Rotation.from_matrix(R).as_quat()
        assert np.allclose(q, ref, atol=1e-9) or np.allclose(q, -ref, atol=1e-9)
    qs = rots.as_quat() * 3.0  # not normalised: quat_to_rotmat normalises
    assert np.allclose(quat_to_rotmat(qs), mats, atol=1e-12)
    assert quat_to_rotmat(qs.reshape(5, 101, 4)).shape == (5, 101, 3, 3)


def test_plane_homographies_carry_pixels_as_the_plane_points_project():
    """geometry.plane_homographies: a pixel of camera a carried by the homography of a landmark's plane lands
    where its ray's meeting with that plane (geometry.plane_points) projects into camera b."""
    from favormap.geometry import apply_homographies, plane_homographies, plane_points, project

    rng = np.random.default_rng(3)
    K = np.array([[500.0, 0, 320], [0, 480.0, 240], [0, 0, 1]])
    Ta = look_at(np.array([0.0, -2.0, 0.3]), np.zeros(3))
    Tb = look_at(np.array([0.8, -1.8, 0.5]), np.zeros(3))
    X = rng.normal(0, 0.2, (6, 3))
    n = rng.normal(size=(6, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    pix = project(K, Ta, X)[:, None] + rng.uniform(-6, 6, (6, 9, 2))
    want = project(K, Tb, plane_points(K, Ta, pix, X, n).reshape(-1, 3)).reshape(pix.shape)
    N = len(X)
    H = plane_homographies(np.repeat(K[None], N, 0), np.repeat(Ta[None], N, 0), np.repeat(K[None], N, 0),
                           np.repeat(Tb[None], N, 0), X, n)  # fmt: skip
    np.testing.assert_allclose(apply_homographies(H, pix), want, atol=1e-8)
    np.testing.assert_allclose(apply_homographies(H, project(K, Ta, X)[:, None])[:, 0], project(K, Tb, X), atol=1e-8)


def test_moved_poses_see_moved_points_where_the_old_poses_saw_the_old_ones():
    from favormap.geometry import is_rigid, look_at, move_poses, project, rotation_about, transform_points

    rng = np.random.default_rng(3)
    X = rng.normal(size=(20, 3)) + [0, 0, 5]
    T = np.stack([look_at(np.array([x, 0.5, 0.0]), np.array([0.0, 0.0, 5.0])) for x in (-1.0, 0.0, 1.0)])
    S = np.eye(4)
    S[:3, :3] = 2.5 * rotation_about(np.array([0.3, 1.0, -0.2]), 0.7)
    S[:3, 3] = (1.0, -2.0, 0.5)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    moved = move_poses(T, S)
    for old, new in zip(T, moved):
        assert is_rigid(new)
        np.testing.assert_allclose(project(K, new, transform_points(S, X)), project(K, old, X), atol=1e-8)
