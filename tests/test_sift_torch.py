"""favormap.features.sift_torch: OpenCV's SIFT descriptors computed by torch (a GPU build's
patches) are OpenCV's, point by point, at every pyramid level and orientation (on the CPU here;
tests/test_cuda.py checks the same on a GPU)."""

from __future__ import annotations

import numpy as np
import pytest

from favormap import features
from favormap.features.base import patch_offsets


@pytest.fixture(scope="module")
def scene():
    from favormap.synthetic import camera_path, make_camera, make_room, render

    image = render(make_room(1), make_camera(320, 240), camera_path(3)[1])[0]
    ex = features.create("sift", max_keypoints=400)
    f = ex.extract(image)
    # training-patch points around 60 keypoints (in each keypoint's own frame, octaves -1 .. 3), points far
    # from any keypoint (the fixed upright size), and points outside the image (clipped to its border)
    rng = np.random.default_rng(0)
    kp = f.keypoints[rng.choice(len(f), 60, replace=False)]
    pts = (kp[:, None] + patch_offsets(7, 3)[None]).reshape(-1, 2)
    far = rng.uniform([0, 0], [320, 240], (400, 2))
    pts = np.concatenate([pts, far, [[-5.0, 10.0], [330.0, 250.0], [0.2, 0.3]]]).astype(np.float32)
    return f, pts


def test_torch_descriptors_are_opencvs(scene):
    f, pts = scene
    opencv = features.create("sift").sample(f, pts)
    mine = features.create("sift", torch_descriptors=True).sample(f, pts)
    assert mine.shape == opencv.shape == (len(pts), 128)
    cos = np.sum(mine * opencv, axis=1)
    # the same descriptors up to the rounding of a float sum taken in another order (a 0..255 bin off by one)
    assert cos.min() > 0.9999 and np.median(cos) > 0.999999, (cos.min(), np.median(cos))
    st = f.dense
    used = np.unique(st.octave)
    assert len(used) >= 6  # the comparison spans several octaves and layers


def test_raw_descriptors_are_opencvs_bins(scene):
    """Before RootSIFT: OpenCV's 0..255 bins, each within one of OpenCV's (> 99 % of the descriptors
    equal in every bin), at any angle."""
    import cv2

    from favormap.features import sift_torch

    f, _ = scene
    st = f.dense
    xy = f.keypoints - 0.5
    angle = np.random.default_rng(1).uniform(0, 360, len(xy)).astype(np.float32)  # every orientation bin
    kps = [
        cv2.KeyPoint(float(x), float(y), float(s), float(a), 0, int(o))
        for (x, y), s, a, o in zip(xy, st.size, angle, st.octave)
    ]
    anchor = cv2.KeyPoint(160.0, 120.0, 3.2, 0, 0, (-1 & 255) | (1 << 8))  # the pyramid from the upsampled octave
    out, ref = cv2.SIFT_create().compute(st.gray, kps + [anchor])
    assert len(out) == len(kps) + 1
    mine = sift_torch.describe(st.gray, xy, st.size, angle, st.octave)
    diff = np.abs(mine - ref[:-1])
    exact = np.mean(diff.max(axis=1) == 0)
    assert diff.max() <= 1 and exact > 0.99, (diff.max(), exact)


def test_sift_patches_are_gpu_tasks_only_where_the_executor_has_a_gpu(small_sequence, monkeypatch):
    """The build routes SIFT's patch sampling to the GPU task path exactly when the executor has a GPU."""
    from favormap.build import ExtractorSpec, PatchTask, sample_patches, training_rays
    from favormap.executor import LocalExecutor

    class Recording(LocalExecutor):
        def __init__(self, gpu):
            super().__init__("cpu", workers=1)
            self.gpu, self.flags = gpu, []

        @property
        def has_gpu(self):
            return self.gpu

        def map_each(self, fn, tasks, total, sink, gpu=False, progress=None):
            self.flags.append((fn.__name__, gpu))
            return super().map_each(fn, tasks, total, sink, gpu, progress)

    from favormap.build import BuildConfig, extract_sequence, select_landmarks, track_frames, triangulate_tracks

    seq = small_sequence
    cfg = BuildConfig(extractor="sift", max_keypoints=300, max_side=0)
    spec = ExtractorSpec("sift", 300)
    ff = extract_sequence(seq, spec, 0)
    lms = select_landmarks(triangulate_tracks(track_frames(ff, cfg), ff, cfg), 50)
    got = {}
    for gpu in (False, True):
        ex = Recording(gpu)
        got[gpu] = training_rays(lms, ff, spec, 3, executor=ex).targets
        assert ("patch_targets", gpu) in ex.flags
    np.testing.assert_array_equal(got[True], got[False])  # a GPU task on a CPU device: OpenCV, the same
    # a task given a GPU device samples through torch (here: "cpu:0", torch on the CPU), with OpenCV's result
    task = PatchTask(spec, ff.features[0], ff.features[0].keypoints[:20] + 1.0)
    from favormap.features import sift_torch

    calls = []
    real = sift_torch.describe
    monkeypatch.setattr(sift_torch, "describe", lambda *a, **k: calls.append(k) or real(*a, **k))
    opencv = sample_patches(task, device="cpu")
    assert not calls
    on_device = sample_patches(task, device="cpu:0")
    assert len(calls) == 1 and np.sum(on_device * opencv, axis=1).min() > 0.9999


def test_levels_smaller_than_the_window_and_points_on_the_border():
    """A 20 x 24 image: OpenCV's descriptors up to the octave whose image is a few pixels wide
    (zero where no pixel of the window lies inside it), and finite zeros beyond (where OpenCV's
    own pyramid cannot be built)."""
    import cv2

    from favormap.features import sift_torch

    gray = np.random.default_rng(0).integers(0, 255, (20, 24), dtype=np.uint8)
    xy = np.array([[10, 10], [0, 0], [23, 19]], np.float32)
    for octave in (-1, 0, 2, 4, 7):
        packed = np.full(3, (octave & 255) | (1 << 8), np.int64)
        size = np.full(3, 3.2 * 2 ** (octave + 1 / 3), np.float32)
        mine = sift_torch.describe(gray, xy, size, np.zeros(3, np.float32), packed)
        assert mine.shape == (3, 128) and np.isfinite(mine).all()
        if octave <= 4:
            kps = [cv2.KeyPoint(float(x), float(y), float(s), 0, 0, int(o)) for (x, y), s, o in zip(xy, size, packed)]
            _, ref = cv2.SIFT_create().compute(gray, kps + [cv2.KeyPoint(12, 10, 3.2, 0, 0, (-1 & 255) | (1 << 8))])
            np.testing.assert_array_equal(mine, ref[:3])
        else:
            assert not mine.any()
