"""Voxel rendering at views away from the mapping path, sparse vs dense rendering, presets.

The view test maps a short segment of the synthetic orbit (exact poses) and queries views that
leave it (further along the orbit, raised and lowered cameras re-aimed at the same content). For
every visible, unoccluded landmark the truth is the descriptor extracted at its projection in the
query image. With the default VoxelConfig the rendered descriptor must beat the landmark's mean
descriptor (what the map stores) by a clear margin at those views and the descriptor of the nearest
training view at the views >= 10 deg from it. (Without the centre and prior rays, ``centre_rays=0, prior_rays=0``,
rendered and mean are within 0.002 of each other and 0.015 below the nearest view;
``python tools/bench_novel_view.py --variants all`` prints the table.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch


def _moved(T, dz, look=1.6):
    from favormap import geometry
    from favormap.synthetic.scene import UP

    wfc = geometry.inverse(T)
    eye, fwd = wfc[:3, 3], wfc[:3, 2]
    return geometry.look_at(eye + np.array([0.0, 0.0, dz]), eye + look * fwd, up=UP)


def _view_pairs(voxel_config, tmp_path, n_train=14, start=8, extractor="xfeat"):
    """(rendered, nearest-view, mean-descriptor) cosines to the truth and the angle to the nearest
    training view of every (query, landmark) pair."""
    from favormap import features
    from favormap.build import BuildConfig, build_map
    from favormap.geometry import camera_centers, project
    from favormap.ops.spatial import project_inside
    from favormap.synthetic import camera_path, make_room, render, write_sequence
    from favormap.voxels import render_from_camera

    scene = make_room(0)
    path = camera_path(40, step=0.07, seed=0)
    train = [path[i] for i in range(start, start + n_train)]
    seq = write_sequence(tmp_path / "seq", poses=train, width=320, height=240, scene=scene)
    cfg = BuildConfig(extractor=extractor, max_keypoints=1024, max_side=0, max_landmarks=300, voxel=voxel_config)
    m = build_map(seq, cfg)
    cam = seq.cameras[0]
    lo, hi = start, start + n_train - 1
    queries = [
        path[lo - 6],
        path[lo - 3],
        path[hi + 3],
        path[hi + 6],
        path[hi + 9],
        _moved(path[lo + 3], 0.5),
        _moved(path[hi - 3], -0.6),
        _moved(path[hi + 5], 0.45),
        _moved(path[lo - 4], -0.6),
    ]
    ex = features.create(m.extractor)
    R3 = m.grid_resolution**3
    desc = torch.as_tensor(m.descriptors.reshape(m.num_landmarks, R3, -1))
    dens = torch.as_tensor(m.density.reshape(m.num_landmarks, R3))
    obs_c = camera_centers(m.cam_from_world[m.track_frame])
    obs_u = obs_c - m.positions[m.track_landmark]
    obs_u /= np.linalg.norm(obs_u, axis=1, keepdims=True)
    train_feats = {}
    out = {"rendered": [], "nearest": [], "mean": [], "angle": []}
    for T in queries:
        assert scene.camera_is_valid(camera_centers(T))
        img, depth = render(scene, cam, T)
        vis = np.flatnonzero(project_inside(m.positions, cam, T, margin_px=8))
        uv, z = project(cam.K, T, m.positions[vis], with_depth=True)
        ui = np.clip(uv.astype(int), 0, [cam.width - 1, cam.height - 1])
        ok = np.abs(depth[ui[:, 1], ui[:, 0]] - z) < 0.02 * z + 0.005  # not occluded
        vis, uv = vis[ok], uv[ok]
        truth = ex.sample(ex.extract(img), uv)
        c = camera_centers(T)
        rendered = render_from_camera(
            desc[vis],
            dens[vis],
            torch.as_tensor(m.positions[vis]).float(),
            torch.as_tensor(m.voxel_size[vis]),
            torch.as_tensor(c).float(),
            m.render_samples,
        ).numpy()
        nearest = np.zeros_like(truth)
        frame_of = np.zeros(len(vis), int)  # each landmark's nearest training frame
        for k, j in enumerate(vis):
            obs = np.flatnonzero(m.track_landmark == j)
            u = (c - m.positions[j]) / np.linalg.norm(c - m.positions[j])
            ang = np.degrees(np.arccos(np.clip(obs_u[obs] @ u, -1, 1)))
            frame_of[k] = m.track_frame[obs[np.argmin(ang)]]
            out["angle"].append(ang.min())
        for f in np.unique(frame_of):  # one sample() call per frame (SIFT's costs ~10 ms a call)
            if f not in train_feats:
                from favormap.io import load_image

                train_feats[f] = ex.extract(load_image(seq.frames[f].image_path, cam, 0)[0])
            ks = np.flatnonzero(frame_of == f)
            nearest[ks] = ex.sample(train_feats[f], project(cam.K, m.cam_from_world[f], m.positions[vis[ks]]))
        out["rendered"].append(np.sum(rendered * truth, 1))
        out["nearest"].append(np.sum(nearest * truth, 1))
        out["mean"].append(np.sum(m.mean_descriptor[vis] * truth, 1))
    return {k: np.concatenate(v) if k != "angle" else np.array(v) for k, v in out.items()}


@pytest.mark.parametrize(
    "extractor, quality",
    [
        ("xfeat", "fast"),
        ("xfeat", "quick"),
        pytest.param(
            "sift",
            "fast",
            marks=pytest.mark.xfail(
                strict=True,
                reason="target not met for SIFT: rendered vs mean descriptor +0.0030 (>= 10 deg; needs +0.01), "
                "+0.0042 (all), vs nearest view +0.0143 on this scene; SIFT's "
                "track mean predicts extrapolated views almost as well as the grid",
            ),
        ),
    ],
)
def test_rendered_descriptors_beat_the_mean_descriptor_away_from_the_mapping_path(tmp_path, extractor, quality):
    from favormap.voxels import VoxelConfig

    r = _view_pairs(VoxelConfig.preset(quality), tmp_path, extractor=extractor)
    far = r["angle"] >= 10.0
    assert far.sum() >= 300 and (~far).sum() >= 300, (far.sum(), (~far).sum())
    gain_far = r["rendered"][far].mean() - r["mean"][far].mean()
    gain_all = r["rendered"].mean() - r["mean"].mean()
    vs_nearest_far = r["rendered"][far].mean() - r["nearest"][far].mean()
    vs_nearest = r["rendered"].mean() - r["nearest"].mean()
    summary = (
        f"gain over mean: >=10 deg {gain_far:.4f}, all {gain_all:.4f}; "
        f"vs nearest view: >=10 deg {vs_nearest_far:.4f}, all {vs_nearest:.4f}"
    )
    print(summary)
    # measured (XFeat, 2026-11-26): fast 0.0172 / 0.0174; +0.0017 / +0.0014; quick 0.0183 / 0.0182;
    # +0.0020 / +0.0013 (former training: 0.0015 / 0.0012 / -0.015 overall; the closed form at the
    # initial density 1 instead of the quick preset's 20: -0.0005 against the nearest view at >= 10 deg
    # with 3 x 3 patches, -0.0009 with 7 x 7, so it would fail here)
    assert gain_far >= 0.01, summary
    assert gain_all >= 0.01, summary
    assert vs_nearest_far > 0.0, summary  # beats the nearest training view where views are extrapolated
    assert vs_nearest >= -0.003, summary


def test_rendering_equals_explicit_sample_interpolation():
    """The composite-stencil renderer equals interpolating every sample's descriptor and density
    from its 8 cube corners and alpha-compositing them (paper eqs. 3-5), for several grid sizes,
    with a ray that misses the cube rendering to zero."""
    import torch.nn.functional as F

    from favormap.voxels.render import box_intersections, ray_stencils, render

    g = torch.Generator().manual_seed(0)
    for R in (2, 3, 5):
        G, K, N, C = 3, 7, 12, 5
        d = torch.randn(G, K, 3, generator=g)
        o = 0.5 - 2.0 * F.normalize(d, dim=-1) + 0.3 * torch.randn(G, K, 3, generator=g)
        o[:, -1] = torch.tensor([3.0, 3.0, 3.0])  # a ray that misses the box
        d[:, -1] = torch.tensor([1.0, 0.0, 0.0])
        desc, dens = torch.randn(G, R**3, C, generator=g), torch.randn(G, R**3, generator=g)
        a, op_a = render(desc, dens, *ray_stencils(o, d, R, N))
        # explicit: sample points, corner lookup, alpha compositing
        du = F.normalize(d, dim=-1)
        tn, tf, hit = box_intersections(o, du)
        span = (tf - tn).clamp_min(0)
        t = tn[..., None] + span[..., None] * (torch.arange(N) + 0.5) / N
        p = (o[..., None, :] + t[..., None] * du[..., None, :]).clamp(0, 1) * (R - 1)
        i0 = p.floor().clamp(0, R - 2).long()
        f = p - i0
        vals, sig = torch.zeros(G, K, N, C), torch.zeros(G, K, N)
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    c = torch.tensor([cx, cy, cz])
                    wgt = torch.where(c.bool(), f, 1 - f).prod(-1)
                    node = ((i0 + c) * torch.tensor([R * R, R, 1])).sum(-1)
                    for gi in range(G):
                        vals[gi] += wgt[gi, ..., None] * desc[gi][node[gi]]
                        sig[gi] += wgt[gi] * dens[gi][node[gi]]
        alpha = 1 - torch.exp(-F.softplus(sig) * (span / N)[..., None])
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[..., :1]), 1 - alpha[..., :-1] + 1e-10], -1), -1)
        wt = trans * alpha * hit[..., None]
        torch.testing.assert_close(a, (wt[..., None] * vals).sum(-2), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(op_a, wt.sum(-1), atol=1e-5, rtol=1e-5)
        assert torch.all(a[:, -1] == 0) and torch.all(op_a[:, -1] == 0)


def test_training_losses_equal_the_losses_of_rendered_descriptors():
    """The training loss works on composite stencils (p.t = a (D t), |p|^2 = a D D^T a): it must
    equal the squared distance and cosine of the explicitly rendered descriptors."""
    import torch.nn.functional as F

    from favormap.voxels.train import _losses

    g = torch.Generator().manual_seed(1)
    G, K1, K2, R3, C = 4, 5, 3, 27, 16
    a = torch.rand(G, K1 + K2, R3, generator=g) / R3
    D = torch.randn(G, R3, C, generator=g)
    t1 = F.normalize(torch.randn(G, K1, C, generator=g), dim=-1)
    t2 = 0.5 * F.normalize(torch.randn(G, K2, C, generator=g), dim=-1)
    t = torch.cat([t1, t2], 1)
    se, cos = _losses(a, D, [t1, t2], (t * t).sum(-1))
    p = torch.bmm(a, D)
    torch.testing.assert_close(se, ((p - t) ** 2).sum(-1), atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(cos, F.cosine_similarity(p, t, dim=-1), atol=1e-5, rtol=1e-4)


def test_quality_presets_and_cli_flags():
    import argparse

    from favormap.cli import build as cli_build
    from favormap.voxels import QUALITY_PRESETS, VoxelConfig

    assert set(QUALITY_PRESETS) == {"quick", "balanced", "fast", "reference"}
    ref = VoxelConfig.preset("reference")
    assert (ref.iterations, ref.rays_per_landmark, ref.box_factor, ref.solver) == (2000, 1024, 12.0, "adam")
    assert VoxelConfig.preset("fast") == VoxelConfig() and VoxelConfig().solver == "adam"
    assert VoxelConfig.preset("quick") == VoxelConfig(solver="lstsq", patch_size=3, density_init=20.0)
    balanced = VoxelConfig(solver="lstsq", patch_size=7, density_init=20.0, lstsq_ridge=0.03)
    assert VoxelConfig.preset("balanced") == balanced
    with pytest.raises(ValueError):
        VoxelConfig.preset("slow")
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers()
    cli_build.register(sub)
    args = ap.parse_args(
        ["build", "seq", "-o", "x.h5", "--quality", "reference", "--iterations", "50", "--device", "cpu"]
    )
    cfg = cli_build.config_from_args(args).voxel
    assert (cfg.iterations, cfg.rays_per_landmark, cfg.box_factor, cfg.resolution) == (50, 1024, 12.0, 3)
    # flags left out take BuildConfig's defaults; given ones override them
    from favormap.build import BuildConfig

    plain = cli_build.config_from_args(ap.parse_args(["build", "seq", "-o", "x.h5"]))
    assert (plain.min_track, plain.max_landmarks) == (BuildConfig().min_track, BuildConfig().max_landmarks)
    given = cli_build.config_from_args(
        ap.parse_args(["build", "seq", "-o", "x.h5", "--min-track", "6", "--max-landmarks", "700"])
    )
    assert (given.min_track, given.max_landmarks) == (6, 700)
    assert (plain.match_window, plain.max_epipolar_px) == (BuildConfig().match_window, BuildConfig().max_epipolar_px)
    tracking = cli_build.config_from_args(
        ap.parse_args(["build", "seq", "-o", "x.h5", "--match-window", "3", "--max-epipolar", "2"])
    )
    assert (tracking.match_window, tracking.max_epipolar_px) == (3, 2.0)
    # --exact-poses: aligned tracks and stored patches unless given, in the CLI and the API
    exact = cli_build.config_from_args(ap.parse_args(["build", "seq", "-o", "x.h5", "--exact-poses"]))
    assert (exact.exact_poses, exact.refine_window, exact.align_patches) == (True, 9, 20)
    assert (plain.exact_poses, plain.refine_window, plain.align_patches) == (False, 0, 0)
    exact = cli_build.config_from_args(
        ap.parse_args(["build", "seq", "-o", "x.h5", "--exact-poses", "--refine-window", "5", "--align-patches", "12"])
    )
    assert (exact.refine_window, exact.align_patches) == (5, 12)
    assert (BuildConfig(exact_poses=True).refine_window, BuildConfig(exact_poses=True).align_patches) == (9, 20)
    # DISK and ALIKED maps store their observations' pixels and ask the localizer to align (build.localize_defaults)
    from favormap.build import localize_defaults

    assert [BuildConfig(extractor=ex).align_patches for ex in ("sift", "xfeat", "disk", "aliked")] == [0, 0, 20, 20]
    assert BuildConfig(extractor="disk", align_patches=0).align_patches == 0
    aligns = [localize_defaults(BuildConfig(extractor=ex))["align"] for ex in ("sift", "xfeat", "disk", "aliked")]
    assert aligns == [False, False, True, True]
    assert not localize_defaults(BuildConfig(extractor="disk", align_patches=0))["align"]  # nothing to align to
    assert localize_defaults(BuildConfig(exact_poses=True))["align"]
    for ex, r in (("sift", 0), ("disk", 20)):
        args = ap.parse_args(["build", "seq", "-o", "x.h5", "--extractor", ex])
        assert cli_build.config_from_args(args).align_patches == r
    # the default preset follows the extractor, the same in the CLI and the API: SIFT balanced, the learned
    # extractors Adam ("fast")
    from favormap.features import policy_of

    quality = [policy_of(ex).training_quality for ex in ("sift", "disk", "xfeat")]
    assert quality == ["balanced", "fast", "fast"]
    for ex in ("sift", "disk", "xfeat"):
        args = ap.parse_args(["build", "seq", "-o", "x.h5", "--device", "cpu", "--extractor", ex])
        want = VoxelConfig.preset(policy_of(ex).training_quality)
        assert cli_build.config_from_args(args).voxel == want == BuildConfig(extractor=ex).voxel
    assert BuildConfig().voxel == VoxelConfig.preset("balanced")
    given = BuildConfig(extractor="disk", voxel=VoxelConfig.preset("quick"))  # a given preset stays
    assert given.voxel == VoxelConfig.preset("quick")
    assert (BuildConfig().match_window, BuildConfig().max_epipolar_px) == (10, None)
    # the epipolar limit is measured unless given, no less than the extractor's floor (DISK's keypoints are
    # less precise), in the CLI and the API; a given limit stays
    from favormap.build import default_max_epipolar

    assert [default_max_epipolar(ex) for ex in ("sift", "disk", "xfeat")] == [1.0, 2.0, 1.0]
    for ex in ("sift", "disk", "xfeat"):
        args = ap.parse_args(["build", "seq", "-o", "x.h5", "--extractor", ex])
        assert cli_build.config_from_args(args).max_epipolar_px is None
        assert BuildConfig(extractor=ex).max_epipolar_px is None
        args = ap.parse_args(["build", "seq", "-o", "x.h5", "--extractor", ex, "--max-epipolar", "1.5"])
        assert cli_build.config_from_args(args).max_epipolar_px == 1.5
    assert BuildConfig(extractor="disk", max_epipolar_px=1.0).max_epipolar_px == 1.0
    args = ap.parse_args(["build", "seq", "-o", "x.h5", "--quality", "quick"])
    assert cli_build.config_from_args(args).voxel.solver == "lstsq"
    # patch interpolation: per extractor (SIFT describes half of its full, odd patches), unless asked
    from favormap.voxels.config import voxel_config_for

    assert BuildConfig().voxel.patch_interp is None
    assert voxel_config_for(BuildConfig().voxel, "sift").patch_interp is True
    assert voxel_config_for(BuildConfig().voxel, "disk").patch_interp is False
    for over in (dict(patch_stride=3), dict(patch_size=6), dict(patch_interp=False)):
        assert voxel_config_for(VoxelConfig.preset("balanced", **over), "sift").patch_interp is False, over
    exact = cli_build.config_from_args(ap.parse_args(["build", "seq", "-o", "x.h5", "--exact-patches"]))
    assert exact.voxel.patch_interp is False and plain.voxel.patch_interp is None


def test_reference_preset_trains_in_memory_bounded_groups():
    """The reference budget (1,024 + 512 rays per landmark and iteration) runs through the same
    code, landmarks in groups of at most max_batch_rays rays; grouping does not change the result."""
    from favormap.features import patch_offsets
    from favormap.geometry import camera_centers, look_at
    from favormap.voxels import TrainingRays, VoxelConfig, train_voxels

    rng = np.random.default_rng(0)
    L, C, S, n_cams = 5, 8, 7, 6
    X = rng.uniform([-1, -1, 4], [1, 1, 6], size=(L, 3))
    T = [look_at([x, 0.0, 0.0], [0, 0, 5], up=(0, -1, 0)) for x in np.linspace(-1, 1, n_cams)]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    offs = patch_offsets(S)
    obs_lm, origins, dirs, targets = [], [], [], []
    for j in range(L):
        for Ti in T:
            p = K @ (Ti[:3, :3] @ X[j] + Ti[:3, 3])
            uv = p[:2] / p[2] + offs
            dirs.append(np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T @ Ti[:3, :3])
            origins.append(camera_centers(Ti))
            obs_lm.append(j)
            t = rng.normal(size=(len(offs), C))
            targets.append(t / np.linalg.norm(t, axis=1, keepdims=True))
    dist = np.linalg.norm(X[:, None] - np.array(origins[:n_cams])[None], axis=2).min(1)
    data = TrainingRays(
        X,
        12 * dist / 500.0,
        np.array(obs_lm),
        np.array(origins),
        np.array(dirs, np.float32),
        np.array(targets, np.float32),
    )
    a = train_voxels(data, VoxelConfig.preset("reference", iterations=3))
    b = train_voxels(data, VoxelConfig.preset("reference", iterations=3, max_batch_rays=2000))  # 1 landmark per group
    torch.testing.assert_close(a.descriptors, b.descriptors, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(a.density, b.density, atol=1e-5, rtol=1e-4)


def test_a_registered_extractor_states_its_own_policy(monkeypatch):
    """A user's extractor registered with its own ExtractorPolicy gets it everywhere a build and a map's
    localizer resolve defaults: epipolar floor, stored patches (and the localizer's alignment), training preset,
    view prior, patch interpolation; one without a policy gets ExtractorPolicy's defaults."""
    from favormap import features
    from favormap.build import BuildConfig, default_max_epipolar, localize_defaults
    from favormap.errors import InputError
    from favormap.features import ExtractorPolicy
    from favormap.features.sift import SIFTExtractor
    from favormap.voxels import VoxelConfig
    from favormap.voxels.config import voxel_config_for

    monkeypatch.setattr(features.base, "_REGISTRY", dict(features.base._REGISTRY))

    @features.register("toy-precise")
    class Toy(SIFTExtractor):
        policy = ExtractorPolicy(
            keypoint_precision_px=1.5, align_patches=6, training_quality="quick", view_prior_deg=5.0, patch_interp=True
        )

    @features.register("toy-plain")
    class Plain(SIFTExtractor):
        policy = ExtractorPolicy()

    cfg = BuildConfig(extractor="toy-precise")
    assert (cfg.align_patches, cfg.voxel.solver, cfg.voxel.patch_size) == (6, "lstsq", 3)
    assert default_max_epipolar("toy-precise") == 1.5 and localize_defaults(cfg)["align"]
    full = voxel_config_for(VoxelConfig.preset("balanced"), "toy-precise")
    assert (full.prior_mean_deg, full.patch_interp) == (5.0, True)
    plain = BuildConfig(extractor="toy-plain")
    assert (plain.align_patches, plain.voxel) == (0, VoxelConfig.preset("fast"))
    assert default_max_epipolar("toy-plain") == 1.0 and not localize_defaults(plain)["align"]
    assert voxel_config_for(plain.voxel, "toy-plain").prior_mean_deg == 30.0
    with pytest.raises(InputError, match="unknown feature extractor"):
        BuildConfig(extractor="no-such-extractor")
    with pytest.raises(InputError, match="align_patches"):
        ExtractorPolicy(align_patches=-1)
