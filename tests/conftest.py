"""Shared fixtures: small synthetic scenes and maps built by code (no external data)."""

from __future__ import annotations

import os
import socket

import pytest

os.environ.setdefault("RERUN_ANALYTICS", "false")


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

    vox = VoxelConfig(iterations=over.pop("iterations", 120))
    cfg = BuildConfig(max_keypoints=1024, max_side=0, max_landmarks=over.pop("max_landmarks", 400), voxel=vox)
    for k, v in over.items():
        setattr(cfg, k, v)
    return cfg


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
