"""The extractor registry loads built-in extractors on first use: importing favormap.features and
creating / using SIFT never imports torch (a torch-free one-shot localization path for SIFT maps),
while XFeat / DISK and the old attribute paths keep working."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from favormap import features
from favormap.errors import InputError

CHILD = """
import sys
import cv2
import numpy as np
import favormap.features as f

after_import = "torch" in sys.modules
rng = np.random.default_rng(0)
img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), (0, 0), 2.0)
img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)  # blurred noise: restore the contrast
ex = f.create("sift", max_keypoints=500)
feats = ex.extract(img)
pts = np.concatenate([feats.keypoints[:50] + [1.0, 0.0], rng.uniform(0, [320, 240], (50, 2))]).astype(np.float32)
desc = ex.sample(feats, pts)
assert desc.shape == (100, 128) and np.isfinite(desc).all(), desc.shape
assert f.extractor_class("sift") is type(ex) and int(f.sift.octave_of_size(12.0)) > 0
print("KEYPOINTS", len(feats))
print("AVAILABLE", ",".join(f.available()))
print("TORCH", after_import, "torch" in sys.modules)
"""


def test_sift_extractor_never_imports_torch():
    r = subprocess.run(
        [sys.executable, "-c", CHILD],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "RERUN_ANALYTICS": "false"},
    )
    assert r.returncode == 0, r.stderr
    out = dict(line.split(" ", 1) for line in r.stdout.splitlines() if " " in line)
    assert int(out["KEYPOINTS"]) > 50, r.stdout
    assert {"disk", "sift", "xfeat"} <= set(out["AVAILABLE"].split(",")), r.stdout
    assert out["TORCH"] == "False False", r.stdout


def test_available_lists_the_built_ins_before_they_are_loaded():
    assert {"disk", "sift", "xfeat"} <= set(features.available())
    assert features.available() == sorted(features.available())


def test_xfeat_is_created_on_first_use():
    ex = features.create("xfeat", max_keypoints=64)
    assert ex.name == "xfeat" and ex.channels == 64
    assert features.extractor_class("xfeat") is type(ex)
    assert features.xfeat.XFeatExtractor is type(ex)


def test_unknown_names_raise_input_error():
    with pytest.raises(InputError, match=r"unknown feature extractor 'nope' \(available: .*sift.*\)"):
        features.create("nope")
    with pytest.raises(InputError, match="unknown feature extractor"):
        features.extractor_class("nope")


def test_old_attribute_paths_still_work():
    assert int(features.sift.octave_of_size(12.0)) == int(features.sift.octave_of_size(np.float32(12.0)))
    for name in ("Extractor", "Features", "available", "create", "patch_offsets", "register"):
        assert hasattr(features, name) and name in features.__all__
    with pytest.raises(AttributeError):
        features.no_such_thing  # noqa: B018


def test_register_adds_and_overrides(monkeypatch):
    monkeypatch.setattr(features.base, "_REGISTRY", dict(features.base._REGISTRY))

    @features.register("toy")
    class Toy(features.Extractor):
        channels = 2

        def extract(self, image):
            raise NotImplementedError

        def sample(self, feats, points):
            raise NotImplementedError

    assert "toy" in features.available() and isinstance(features.create("toy"), Toy)
    assert Toy.name == "toy"

    # a user's extractor under a built-in's name wins, even if the built-in's module registers later
    builtin = features.sift.SIFTExtractor
    monkeypatch.setitem(features.base._REGISTRY, "sift", Toy)
    features.register("sift")(builtin)  # what the built-in module's decorator does on import
    assert features.extractor_class("sift") is Toy
    monkeypatch.delitem(features.base._REGISTRY, "sift")
    features.register("sift")(builtin)
    assert features.extractor_class("sift") is builtin
