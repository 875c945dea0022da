"""Shared fixtures: small synthetic scenes and maps built by code (no external data)."""

from __future__ import annotations

import os
import socket

import pytest

os.environ.setdefault("RERUN_ANALYTICS", "false")
if os.environ.get("PYTEST_XDIST_WORKER_COUNT"):  # pytest -n N: the CPUs shared among the N workers
    _cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _cpus // int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))))


@pytest.fixture
def no_network(monkeypatch):
    """Any attempt to open a network connection fails the test (weights must come from installed files)."""

    def refuse(*a, **k):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


SMALL = dict(n_frames=16, width=320, height=240, fov_deg=60.0, seed=0)


def small_build_config(**over):
    from favormap.build import BuildConfig
    from favormap.voxels import VoxelConfig

    # every setting goes through the constructor, so that the fields left out resolve from the extractor's
    # policy as a user's build resolves them (stored patches, epipolar floor)
    vox = VoxelConfig(iterations=over.pop("iterations", 120))
    return BuildConfig(**{"max_keypoints": 1024, "max_side": 0, "max_landmarks": 400, "voxel": vox, **over})


def assert_samples_at_full_resolution(ex, f, image, near_min: float, far_max: float) -> None:
    """What a full-resolution learned extractor (DISK, ALIKED) promises of the features ``f`` it extracted
    from ``image``: > 200 unit 128-d descriptors, strongest first, sub-pixel keypoints inside the image;
    sampling at the keypoints gives their descriptors; half a pixel away the median cosine stays above
    ``near_min``, 3 px away it falls below ``far_max`` (a 1/8-resolution map, e.g. XFeat's, interpolates
    between cells 8 px apart and barely changes over 3 px); any position, including outside the image
    (clamped), and none at all can be sampled."""
    import numpy as np

    h, w = image.shape[:2]
    assert len(f) > 200 and f.descriptors.shape == (len(f), 128) and f.image_size == (w, h)
    np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(f.scores) <= 0)  # strongest first
    assert np.all((f.keypoints > 0) & (f.keypoints < [w, h]))
    assert np.any(np.abs(f.keypoints - np.round(f.keypoints - 0.5) - 0.5) > 0.01)  # sub-pixel positions
    np.testing.assert_array_equal(ex.sample(f, f.keypoints), f.descriptors)
    near = np.sum(ex.sample(f, f.keypoints + [0.5, 0.0]) * f.descriptors, 1)
    far = np.sum(ex.sample(f, f.keypoints + [3.0, 0.0]) * f.descriptors, 1)
    assert np.median(near) > near_min and np.median(far) < far_max, (np.median(near), np.median(far))
    assert ex.sample(f, np.array([[-4.0, -4.0], [w + 9.0, h + 9.0]], np.float32)).shape == (2, 128)
    assert ex.sample(f, np.zeros((0, 2), np.float32)).shape == (0, 128)


def localize_perturbed(loc, frames, trans=0.2, deg=8.0, seed=0):
    """(N, 2) translation / rotation errors of ``loc`` on ``frames`` from priors moved by ``trans``
    units and ``deg`` degrees; every query must succeed."""
    import numpy as np

    from favormap.geometry import perturb_pose, pose_error

    rng = np.random.default_rng(seed)
    errs = []
    for fr in frames:
        res = loc.localize(fr.image_path, perturb_pose(fr.cam_from_world, trans, deg, rng))
        assert res.success, res.message
        errs.append(pose_error(res.cam_from_world, fr.cam_from_world))
    return np.array(errs)


@pytest.fixture(scope="module")
def views():
    """Two renders of the synthetic room (RGB, depth) and their camera and poses."""
    from favormap.synthetic import camera_path, make_camera, make_room, render

    room, cam, path = make_room(0), make_camera(320, 240), camera_path(12)
    return cam, [(path[i], *render(room, cam, path[i])) for i in (3, 4)]


def mutual_match_errors(ex, views):
    """Mutual nearest neighbours of ``ex``'s descriptors between the two ``views``: (their number, the
    distance (px) of each from where the first view's keypoint projects into the second, by the rendered
    depth and the exact poses)."""
    import numpy as np

    from favormap.synthetic import backproject, project

    cam, ((pa, ia, da), (pb, ib, _)) = views
    fa, fb = ex.extract(ia), ex.extract(ib)
    s = fa.descriptors @ fb.descriptors.T
    j = s.argmax(1)
    i = np.flatnonzero(s.argmax(0)[j] == np.arange(len(j)))
    j = j[i]
    rows, cols = (fa.keypoints[i, 1] - 0.5).astype(int), (fa.keypoints[i, 0] - 0.5).astype(int)
    X = backproject(cam, pa, fa.keypoints[i], da[rows, cols])
    uv, _ = project(cam, pb, X)
    return len(i), np.linalg.norm(uv - fb.keypoints[j], axis=1)


@pytest.fixture(scope="session")
def small_sequence(tmp_path_factory):
    """A 16-frame 320x240 synthetic room sequence in the favormap layout (with depth maps).

    ``FAVORMAP_SMALL_SEQUENCE=DIR`` reads a copy written beforehand (``tools/gpu_check.sh prepare``)
    instead of rendering it: the renderer needs Open3D, which a GPU machine may lack."""
    pre = os.environ.get("FAVORMAP_SMALL_SEQUENCE")
    if pre:
        from favormap.io import read_sequence

        return read_sequence(pre)
    from favormap.synthetic import write_sequence

    root = tmp_path_factory.mktemp("seq_small")
    return write_sequence(root, depth=True, **SMALL)


@pytest.fixture(scope="session")
def small_map(small_sequence, tmp_path_factory):
    """(MapData, path) of a map built from ``small_sequence``."""
    from favormap.build import build_map
    from favormap.mapfile import write_map

    m = build_map(small_sequence, small_build_config())
    path = tmp_path_factory.mktemp("map_small") / "small.h5"
    write_map(m, path)
    return m, path
