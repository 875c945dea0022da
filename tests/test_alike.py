"""ALIKE extractor (the network is favormap's own, the published weights ship with favormap): every variant's
weights load with the network blocked, descriptors sampled anywhere are consistent with the keypoints',
the published NMS finds the maxima its rounds promise, matches between two views of the synthetic room land
where the geometry says, an ALIKE map localizes; missing or damaged weights are one clear error line
(synthetic scenes only)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import mutual_match_errors

from favormap import features
from favormap.errors import FavormapError


def test_every_variant_loads_its_shipped_weights_with_the_network_blocked(no_network, monkeypatch, views):
    from favormap.features.alike import ALIKEExtractor, weights_path

    monkeypatch.setattr(ALIKEExtractor, "_models", {})  # load afresh, not from another test's cache
    img = views[1][0][1][:96, :128]
    for name, channels in (("alike-t", 64), ("alike-s", 96), ("alike-n", 128), ("alike-l", 128)):
        assert weights_path(name).stat().st_size > 300_000
        ex = features.create(name, max_keypoints=200)
        assert ex.channels == channels and ex.config()["weights"] == name
        f = ex.extract(img)
        assert 10 < len(f) <= 200 and f.descriptors.shape == (len(f), channels)
    # "alike" is the paper's variant, the same network
    ex = features.create("alike")
    assert ex.variant == "alike-l" and ex.model is features.create("alike-l").model
    assert ex.policy == features.policy_of("alike-t")  # one policy for the family


def test_missing_or_damaged_weights_are_one_clear_error(monkeypatch, tmp_path, small_sequence, capsys):
    from favormap.cli import main
    from favormap.features import alike

    monkeypatch.setattr(alike.ALIKEExtractor, "_models", {})
    monkeypatch.setattr(alike, "WEIGHTS", tmp_path)
    with pytest.raises(FavormapError, match="alike-l weights are missing"):
        features.create("alike")
    capsys.readouterr()
    code = main(["build", str(small_sequence.root), "-o", str(tmp_path / "m.h5"), "--extractor", "alike-n"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "alike-n weights are missing" in err[0], err
    assert not (tmp_path / "m.h5").exists()
    good = (alike.Path(alike.__file__).parent / "weights" / "alike-t.pth").read_bytes()
    for damaged in (b"not a torch file", good[: len(good) // 2]):  # foreign bytes, a truncated copy
        (tmp_path / "alike-t.pth").write_bytes(damaged)
        with pytest.raises(FavormapError, match="cannot load the alike-t weights") as e:
            features.create("alike-t")
        assert "\n" not in str(e.value)
    # another variant's weights: the shapes do not fit
    (tmp_path / "alike-s.pth").write_bytes(good)
    with pytest.raises(FavormapError, match="cannot load the alike-s weights"):
        features.create("alike-s")


def test_the_published_nms_adds_maxima_freed_by_clearing():
    """A peak beside a stronger neighbour of a maximum's window is no maximum of its own window; once that
    window is cleared it is, and the published NMS's rounds keep it."""
    from favormap.features.heatmap import local_maxima

    heat = torch.zeros(9, 24)
    heat[4, 10:16] = torch.tensor([0.9, 0.5, 0.95, 0.5, 0.9, 0.8])
    one, _ = local_maxima(heat, 2, 0.2, 10)
    more, scores = local_maxima(heat, 2, 0.2, 10, rounds=2)
    assert one.tolist() == [[12, 4]]
    assert more.tolist() == [[12, 4], [15, 4]] and np.allclose(scores.numpy(), [0.95, 0.8])


def test_sampling_at_keypoints_reproduces_their_descriptors(views):
    from conftest import assert_samples_at_full_resolution

    ex = features.create("alike", max_keypoints=800)
    img = views[1][0][1]
    f = ex.extract(img)
    assert f.scores[-1] > 0.2  # above the threshold
    # full resolution (measured: median cosine 0.984 half a pixel away, 0.78 3 px away)
    assert_samples_at_full_resolution(ex, f, img, near_min=0.97, far_max=0.9)
    # the unit descriptor map bilinearly (grid_sample, corners aligned), normalised again
    w, h = f.image_size
    pts = np.random.default_rng(0).uniform([0.5, 0.5], [w - 0.5, h - 0.5], (300, 2)).astype(np.float32)
    grid = torch.as_tensor(2 * (pts - 0.5) / [w - 1, h - 1] - 1, dtype=torch.float32).view(1, -1, 1, 2)
    dmap = f.dense.dmap.float().permute(2, 0, 1)[None]
    ref = torch.nn.functional.grid_sample(dmap, grid, align_corners=True)[0, :, :, 0].T
    ref = torch.nn.functional.normalize(ref, dim=1).numpy()
    np.testing.assert_allclose(ex.sample(f, pts), ref, atol=1e-5)


def test_matches_between_two_views_land_where_the_geometry_says(views):
    """Mutual nearest neighbours between two renders of the room: most lie within 2 px of where the
    first view's keypoint projects into the second (rendered depth, exact poses)."""
    n, err = mutual_match_errors(features.create("alike", max_keypoints=1000), views)
    # (measured: 459 matches, 98% within 2 px, 94% within 1 px)
    assert n > 250 and np.mean(err < 2.0) > 0.9 and np.mean(err < 1.0) > 0.8, (n, np.mean(err < 2.0))


def test_blank_and_tiny_images_give_no_keypoints_and_still_sample():
    """A uniform image has no maxima above the threshold; images smaller than the network's 32 px stride
    or the NMS window still extract and sample (positions clamped to the image)."""
    ex = features.create("alike-t", max_keypoints=100)
    for shape in [(240, 320, 3), (8, 8, 3), (1, 1, 3)]:
        f = ex.extract(np.full(shape, 128, np.uint8))
        assert len(f) == 0 and f.descriptors.shape == (0, 64)
        d = ex.sample(f, np.array([[0.5, 0.5], [3.0, 2.0]], np.float32))
        assert d.shape == (2, 64) and np.all(np.isfinite(d))
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)


def test_the_sampling_state_goes_through_the_feature_cache(views, tmp_path):
    from favormap.errors import InputError
    from favormap.features.cache import FeatureCache
    from favormap.io.types import Camera

    img = views[1][0][1]
    ex = features.create("alike-t", max_keypoints=300)
    f = ex.extract(img)
    h, w = img.shape[:2]
    pts = np.random.default_rng(1).uniform([0, 0], [w, h], (200, 2)).astype(np.float32)
    with FeatureCache(tmp_path / "c.h5", "alike-t", 300, 0) as cache:
        cache.put("a.png", f, Camera("PINHOLE", w, h, np.array([300.0, 300.0, w / 2, h / 2])), (1, 1))
    with FeatureCache(tmp_path / "c.h5", "alike-t", 300, 0) as cache:
        g = cache.get("a.png")
    np.testing.assert_array_equal(g.keypoints, f.keypoints)
    assert g.dense.dmap.dtype == torch.float16
    np.testing.assert_array_equal(ex.sample(g, pts), ex.sample(f, pts))
    # another variant's state (64 channels) is not an alike-n state
    with pytest.raises(InputError, match="no alike-n features"):
        features.extractor_class("alike-n").state_from_arrays(ex.state_arrays(f.dense))


def test_an_alike_map_localizes(small_sequence, tmp_path):
    """A map of the lightest variant (64 channels: the variant's channels go through the map) localizes."""
    from conftest import localize_perturbed, small_build_config

    from favormap.build import build_map
    from favormap.localize import Localizer
    from favormap.mapfile import Map, write_map

    config = small_build_config(extractor="alike-t", iterations=40, max_landmarks=200, max_keypoints=512)
    m = build_map(small_sequence, config)
    path = tmp_path / "alike.h5"
    write_map(m, path)
    with Map.open(path) as mm:
        assert mm.extractor == "alike-t" and mm.channels == 64
        assert mm.track_patch_radius == 20  # ALIKE's policy: the observations' pixels stored, for the alignment
    loc = Localizer(path)
    assert loc.extractor.variant == "alike-t"
    assert loc.config.match_threshold == loc.extractor.policy.match_threshold == 0.5
    assert loc.config.align  # the map asks for it
    errs = localize_perturbed(loc, small_sequence.frames[2::6])
    assert np.median(errs[:, 0]) < 0.005 and np.median(errs[:, 1]) < 0.2, errs
