"""CUDA paths against the CPU result: voxel rendering, a whole build and localization.

Skipped without a CUDA GPU. On a GPU machine: ``bash tools/gpu_check.sh`` (prepares the data here,
runs these there). Training draws its random numbers from a CPU generator, so a CUDA build sees the
same rays as a CPU build and the results agree up to floating-point noise; the GPU trains several
batches as one task, each batch drawing its own rays, so that too gives the CPU's grids."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import small_build_config

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")]


@pytest.fixture(scope="module")
def maps(small_sequence):
    from favormap.build import build_map

    out = {}
    for dev in ("cpu", "cuda"):
        # batches of 100 landmarks: the CPU trains them one by one, the GPU as one task (train_group)
        out[dev] = build_map(small_sequence, small_build_config(max_landmarks=300, train_batch=100), device=dev)
    return out


def test_build_on_cuda_equals_cpu(maps):
    cpu, gpu = maps["cpu"], maps["cuda"]
    np.testing.assert_allclose(gpu.positions, cpu.positions, atol=1e-9)  # tracking + triangulation: same landmarks
    a = torch.as_tensor(cpu.descriptors, dtype=torch.float64).flatten(1)
    b = torch.as_tensor(gpu.descriptors, dtype=torch.float64).flatten(1)
    cos = torch.nn.functional.cosine_similarity(a, b, dim=1)
    assert float(cos.min()) >= 0.999, f"per-landmark grid cosine CPU vs CUDA: min {float(cos.min()):.5f}"
    np.testing.assert_allclose(gpu.quality, cpu.quality, atol=0.05)
    assert gpu.provenance["executor"]["device"] == "cuda" and len(gpu.positions) > 200  # > 2 batches


def test_render_on_cuda_equals_cpu(maps):
    from favormap.geometry import camera_centers
    from favormap.voxels.render import render_from_camera

    m = maps["cpu"]
    c = camera_centers(m.cam_from_world[0])
    out = {}
    for dev in ("cpu", "cuda"):
        t = lambda x, dt=torch.float32, dev=dev: torch.as_tensor(np.asarray(x), dtype=dt, device=dev)  # noqa: E731
        L, C = len(m.positions), m.channels
        out[dev] = render_from_camera(
            t(m.descriptors).reshape(L, -1, C),
            t(m.density).reshape(L, -1),
            t(m.positions),
            t(m.voxel_size),
            t(c),
            m.render_samples,
        ).cpu()
    assert torch.allclose(out["cuda"], out["cpu"], atol=1e-4)


def test_localize_on_cuda_equals_cpu(maps, small_sequence, tmp_path):
    from favormap.geometry import perturb_pose, pose_error
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map

    path = tmp_path / "m.h5"
    write_map(maps["cpu"], path)
    fr = small_sequence.frames[3]
    prior = perturb_pose(fr.cam_from_world, 0.1, 5, np.random.default_rng(0))
    res = {
        dev: Localizer(path, LocalizeConfig(device=dev)).localize(
            fr.image_path, prior, small_sequence.cameras[fr.camera_id]
        )
        for dev in ("cpu", "cuda")
    }
    assert res["cpu"].success and res["cuda"].success
    t, r = pose_error(res["cuda"].cam_from_world, res["cpu"].cam_from_world)
    assert t < 1e-3 and r < 0.05, (t, r)
    assert abs(res["cuda"].num_inliers - res["cpu"].num_inliers) <= max(2, 0.02 * res["cpu"].num_inliers)


def test_sift_patch_descriptors_on_cuda_are_opencvs(small_sequence):
    """A SIFT build on a GPU computes its patch descriptors there (favormap.features.sift_torch): OpenCV's."""
    import cv2

    from favormap import features
    from favormap.features.base import patch_offsets

    img = cv2.cvtColor(cv2.imread(str(small_sequence.frames[2].image_path)), cv2.COLOR_BGR2RGB)
    f = features.create("sift", max_keypoints=500).extract(img)
    pts = (f.keypoints[:80, None] + patch_offsets(7)[None]).reshape(-1, 2)
    pts = np.concatenate([pts, np.random.default_rng(0).uniform(0, 200, (300, 2))]).astype(np.float32)
    gpu = features.create("sift", device="cuda")
    assert gpu.torch_descriptors
    cos = np.sum(gpu.sample(f, pts) * features.create("sift").sample(f, pts), axis=1)
    assert cos.min() > 0.9995 and np.median(cos) > 0.99999, (cos.min(), np.median(cos))
