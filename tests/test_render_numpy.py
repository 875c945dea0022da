"""favormap.voxels.render_numpy (torch-free, for the localizer's CPU path) against the torch reference
favormap.voxels.render.render_from_camera, which training keeps using for autograd."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from favormap.voxels.render_numpy import render_from_camera_numpy


def _random_grids(seed=0, L=50, R=3, C=16):
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(L, R**3, C)).astype(np.float32)
    # raw densities from very negative (transparent) to very large (opaque), softplus's both tails
    dens = (rng.normal(size=(L, R**3)) * rng.choice([0.5, 3.0, 30.0], size=(L, 1))).astype(np.float32)
    dens[0] = 80.0
    dens[1] = -80.0
    centers = rng.normal(scale=0.5, size=(L, 3)).astype(np.float32)
    sizes = rng.uniform(0.05, 0.5, size=L).astype(np.float32)
    cam = np.array([2.5, -1.5, 1.8], np.float32)
    # edge cases: a ray along a coordinate axis (slab test's 1e-12 guard on zero direction
    # components), a camera inside its landmark's cube, and a camera exactly at a landmark's centre
    centers[2] = cam + np.array([0.0, 0.0, -1.0], np.float32)
    centers[3] = cam + np.array([0.01, -0.02, 0.015], np.float32)
    sizes[3] = 0.3
    centers[4] = cam
    return desc, dens, centers, sizes, cam


def _torch_render(arrays, **kw):
    torch = pytest.importorskip("torch")
    from favormap.voxels.render import render_from_camera

    return render_from_camera(*(torch.from_numpy(a) for a in arrays), **kw).numpy()


@pytest.mark.parametrize("normalize", [True, False])
@pytest.mark.parametrize("n_samples", [12, 16])
def test_matches_torch(normalize, n_samples):
    arrays = _random_grids()
    got = render_from_camera_numpy(*arrays, n_samples=n_samples, normalize=normalize)
    want = _torch_render(arrays, n_samples=n_samples, normalize=normalize)
    want64 = _torch_render([a.astype(np.float64) for a in arrays], n_samples=n_samples, normalize=normalize)
    assert got.dtype == np.float32 and got.shape == want.shape == (50, 16)
    assert np.isfinite(got).all()
    # every ray agrees with torch's float64 rendering of the same (float32) inputs
    np.testing.assert_allclose(got, want64, rtol=0, atol=1e-5)
    if not normalize:
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
        return
    np.testing.assert_allclose(np.delete(np.linalg.norm(got, axis=1), 1), 1.0, atol=1e-5)
    assert not got[1].any()  # density -80 everywhere: fully transparent, renders zero
    # ... and with torch's float32 rendering wherever that one is accurate: on a nearly transparent
    # ray float32's 1 - exp(-sigma * delta) cancels and normalisation magnifies the error (~1e-4
    # at opacity 3e-4, landmark 13 here), which this renderer avoids by compositing in float64
    ones = np.ones((50, 27, 1), np.float64)
    opacity = _torch_render([ones] + [a.astype(np.float64) for a in arrays[1:]], n_samples=n_samples, normalize=False)
    ok = opacity[:, 0] > 1e-3
    assert ok.sum() >= 47
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-5)


def test_matches_torch_float64_and_empty():
    arrays = [a.astype(np.float64) for a in _random_grids(seed=1, R=4, C=8)]
    got = render_from_camera_numpy(*arrays, n_samples=12)
    np.testing.assert_allclose(got, _torch_render(arrays, n_samples=12), rtol=0, atol=1e-6)
    desc, dens, centers, sizes, cam = arrays
    empty = render_from_camera_numpy(desc[:0], dens[:0], centers[:0], sizes[:0], cam, n_samples=12)
    assert empty.shape == (0, 8) and empty.dtype == np.float32


def test_constant_grid_renders_its_descriptor():
    """Interpolation and compositing are convex combinations, so a grid whose nodes all hold e
    renders (opacity * e), which normalises to e, whatever the densities and viewpoint."""
    rng = np.random.default_rng(3)
    L, R, C = 20, 3, 32
    e = rng.normal(size=C).astype(np.float32)
    desc = np.broadcast_to(e, (L, R**3, C)).copy()
    dens = rng.normal(scale=2.0, size=(L, R**3)).astype(np.float32)
    centers = rng.normal(scale=0.3, size=(L, 3)).astype(np.float32)
    sizes = rng.uniform(0.05, 0.5, size=L).astype(np.float32)
    cam = np.array([0.0, -3.0, 0.5], np.float32)
    got = render_from_camera_numpy(desc, dens, centers, sizes, cam, n_samples=12)
    np.testing.assert_allclose(got, np.broadcast_to(e / np.linalg.norm(e), (L, C)), atol=1e-5)
    raw = render_from_camera_numpy(desc, dens, centers, sizes, cam, n_samples=12, normalize=False)
    opacity = raw @ e / (e @ e)
    assert ((opacity > 0) & (opacity <= 1 + 1e-6)).all()
    np.testing.assert_allclose(raw, opacity[:, None] * e, atol=1e-5)


def test_import_does_not_load_torch():
    code = (
        "import sys, favormap.voxels.render_numpy, favormap.voxels as v; "
        "assert callable(v.render_from_camera_numpy); "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_lazy_package_exports():
    import favormap.voxels as voxels

    for name in voxels.__all__:
        assert getattr(voxels, name) is not None
    from favormap.voxels import VoxelConfig, render_from_camera
    from favormap.voxels.config import VoxelConfig as direct_cfg
    from favormap.voxels.render import render_from_camera as direct

    assert render_from_camera is direct and VoxelConfig is direct_cfg
    with pytest.raises(AttributeError):
        voxels.no_such_name  # noqa: B018


def test_ray_stencils_are_trilinear_weights_at_the_samples():
    """ray_stencils (node axis second) gives, for every ray and sample, the trilinear weights of the
    sample point, as trilinear_stencil computes them point by point."""
    import torch

    from favormap.voxels.render import box_intersections, ray_stencils, trilinear_stencil

    g = torch.Generator().manual_seed(3)
    G, K, N, R = 4, 5, 7, 3
    origins = torch.rand(G, K, 3, generator=g, dtype=torch.float64) * 3 - 1
    dirs = torch.nn.functional.normalize(
        0.5 - origins + 0.2 * torch.rand(G, K, 3, generator=g, dtype=torch.float64), dim=-1
    )
    st, delta, hit = ray_stencils(origins, dirs, R, N)
    assert st.shape == (G, R**3, K, N) and hit.any()
    t_near, t_far, _ = box_intersections(origins, dirs)
    t = t_near[..., None] + (t_far - t_near).clamp_min(0)[..., None] * (
        (torch.arange(N, dtype=torch.float64) + 0.5) / N
    )
    points = origins[..., None, :] + t[..., None] * dirs[..., None, :]  # (G, K, N, 3)
    expected = trilinear_stencil(points, R)  # (G, K, N, R^3)
    assert torch.allclose(st.permute(0, 2, 3, 1)[hit], expected[hit], atol=1e-12)
    assert torch.allclose(st.sum(1)[hit], torch.ones(int(hit.sum()), N, dtype=torch.float64))
