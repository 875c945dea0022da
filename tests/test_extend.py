"""extend: a map of the first half of a synthetic capture extended with the second half."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import localize_perturbed, small_build_config

from favormap.mapfile import Map, write_map
from favormap.ops.extend import ExtendConfig, extend_map, moved_sequence

ENV = {**os.environ, "RERUN_ANALYTICS": "false"}


def _config():
    from favormap.voxels import VoxelConfig

    return small_build_config(voxel=VoxelConfig.preset("balanced"))


@pytest.fixture(scope="module")
def halves(small_sequence):
    """(held-out frames, A, B): every 4th frame held out, the others in a first and a second half."""
    n = len(small_sequence)
    held = [i for i in range(n) if i % 4 == 2]
    mapping = [i for i in range(n) if i % 4 != 2]
    half = len(mapping) // 2
    return (
        small_sequence.subset(held),
        small_sequence.subset(mapping[:half]),
        small_sequence.subset(mapping[half:]),
        small_sequence.subset(mapping),
    )


@pytest.fixture(scope="module")
def maps(halves, tmp_path_factory):
    """Paths of the map of A, the map of A + B built at once and A extended with B, and the summary."""
    from favormap.build import build_map

    _, a, b, ab = halves
    root = tmp_path_factory.mktemp("extend")
    write_map(build_map(a, _config()), root / "a.h5")
    write_map(build_map(ab, _config()), root / "full.h5")
    summary = extend_map(root / "a.h5", b, root / "extended.h5", ExtendConfig())
    return root, summary


def test_extend_grows_tracks_and_adds_landmarks_within_the_budget(maps, halves):
    root, s = maps
    _, a, b, _ = halves
    assert s.landmarks_grown > 0 and s.observations_added >= s.landmarks_grown and s.landmarks_added > 0
    with Map.open(root / "a.h5") as ma, Map.open(root / "extended.h5") as me:
        assert me.num_frames == len(a) + len(b) == s.frames_before + s.frames_added
        assert me.frame_names[: len(a)] == ma.frame_names
        assert len(me) == len(ma) + s.landmarks_added - s.landmarks_removed == s.landmarks_after
        # the map held its budget already: new landmarks replace its weakest ones, as a build would choose
        budget = _config().max_landmarks
        assert len(ma) == budget and s.landmarks_removed == s.landmarks_added and len(me) == budget
        kept = len(ma) - s.landmarks_removed
        row_in_a = {int(i): r for r, i in enumerate(ma.ids)}
        rows = np.array([row_in_a[int(i)] for i in me.ids[:kept]])
        assert (np.diff(rows) > 0).all()  # the map's landmarks keep their ids and order; the new ones follow
        assert not np.isin(me.ids[kept:], ma.ids).any()
        removed = np.setdiff1d(np.arange(len(ma)), rows)
        assert ma.track_length[removed].max() <= me.track_length.min()  # the longest tracks are kept
        tl, tf, _ = me.tracks()
        per_lm_new = np.bincount(tl[tf >= len(a)], minlength=len(me))
        assert (per_lm_new[:kept] > 0).sum() == s.landmarks_grown
        assert (per_lm_new[kept:] >= 3).all()  # new landmarks: tracks among the new frames, the longest first
        np.testing.assert_array_equal(np.bincount(tl, minlength=len(me)), me.track_length)
        np.testing.assert_array_equal(np.bincount(tl[tf < len(a)], minlength=len(me))[kept:], 0)
        grown = per_lm_new[:kept] > 0
        assert np.mean(me.track_length[:kept][grown]) > np.mean(ma.track_length[rows[grown]])
        # untouched landmarks keep their grids and observations; grown ones are fine-tuned unless their grids
        # already render what the new frames saw
        untouched = np.flatnonzero(~grown)
        np.testing.assert_array_equal(me.voxels(untouched)[0], ma.voxels(rows[untouched])[0])
        np.testing.assert_array_equal(me.track_length[untouched], ma.track_length[rows[untouched]])
        g = np.flatnonzero(grown)
        same = np.all(me.voxels(g)[0] == ma.voxels(rows[g])[0], axis=tuple(range(1, me.voxels(g)[0].ndim)))
        assert 0 < s.landmarks_retrained < s.landmarks_grown and (~same).sum() == s.landmarks_retrained
        np.testing.assert_array_equal(me.cosine[g[same]], ma.cosine[rows[g[same]]])
        assert me.provenance["operation"] == "extend" and me.provenance["extensions"][-1]["frames_added"] == len(b)
        assert me.provenance["extensions"][-1]["landmarks_removed"] == s.landmarks_removed
        assert me.provenance["config"] == ma.provenance["config"]
        # projections are trusted as far as the map's tracking trusted its poses
        limit = ma.provenance["stats"]["max_epipolar_px"]
        assert me.provenance["extensions"][-1]["match_radius_px"] == pytest.approx(limit)


def test_grids_that_do_not_render_the_new_views_are_retrained(maps, halves, tmp_path):
    """A map whose landmarks claim a perfect fit (cosine 1) explains no new observation: every grown
    landmark is trained again."""
    root, s0 = maps
    with Map.open(root / "a.h5") as ma:
        m = ma.load()
    m.cosine = np.ones_like(m.cosine)
    write_map(m, tmp_path / "perfect.h5")
    s = extend_map(tmp_path / "perfect.h5", halves[2], tmp_path / "out.h5", ExtendConfig())
    assert s.landmarks_grown == s0.landmarks_grown and s.landmarks_retrained == s.landmarks_grown


def test_extending_a_map_with_its_own_frames_warns(maps, halves, tmp_path):
    root, _ = maps
    s = extend_map(root / "a.h5", halves[1], tmp_path / "twice.h5", ExtendConfig(max_landmarks=200))
    n = len(halves[1])
    assert len(s.warnings) == 1 and f"{n} of the {n} new frames are in the map" in s.warnings[0]
    clean = extend_map(root / "a.h5", halves[2], tmp_path / "clean.h5", ExtendConfig(max_landmarks=200))
    assert clean.warnings == []


def test_a_budget_above_every_candidate_keeps_every_landmark_of_the_map(maps, halves, tmp_path):
    root, s0 = maps
    with Map.open(root / "a.h5") as ma:
        n = len(ma)
    s = extend_map(root / "a.h5", halves[2], tmp_path / "big.h5", ExtendConfig(max_landmarks=10**6))
    assert s.landmarks_removed == 0 and s.landmarks_after == n + s.landmarks_added
    assert s.landmarks_added > s0.landmarks_added  # the budget had left out new tracks too
    assert s.landmarks_grown >= s0.landmarks_grown  # no grown landmark is left out either
    with Map.open(root / "a.h5") as ma, Map.open(tmp_path / "big.h5") as me:
        np.testing.assert_array_equal(me.ids[:n], ma.ids)


def test_the_match_radius_follows_the_map_unless_given(maps):
    from favormap.ops.extend import map_build_config, match_radius

    root, _ = maps
    with Map.open(root / "a.h5") as m:
        cfg = map_build_config(m.provenance)
        measured = m.provenance["stats"]["max_epipolar_px"]
        assert cfg.max_epipolar_px is None and match_radius(m, cfg, ExtendConfig()) == pytest.approx(measured)
        cfg.max_epipolar_px = 2.5  # a build given its limit
        assert match_radius(m, cfg, ExtendConfig()) == 2.5
        assert match_radius(m, cfg, ExtendConfig(match_radius_px=0.75)) == 0.75


def test_extended_map_localizes_held_out_frames_like_a_full_build(maps, halves):
    from favormap.localize import LocalizeConfig, Localizer

    root, _ = maps
    held = halves[0]
    errs = {}
    for name in ("full", "extended"):
        with Map.open(root / f"{name}.h5") as m:
            errs[name] = localize_perturbed(Localizer(m, LocalizeConfig()), held.frames)
    t_full, t_ext = np.median(errs["full"][:, 0]), np.median(errs["extended"][:, 0])
    assert t_ext <= 1.5 * t_full + 0.005, (t_ext, t_full)
    assert np.median(errs["extended"][:, 1]) < 1.0


def test_extended_map_validates(maps):
    root, _ = maps
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "validate", str(root / "extended.h5")],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert r.returncode == 0 and ": valid" in r.stdout, r.stdout + r.stderr


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_failure_while_writing_leaves_the_input_untouched_and_no_output(maps, halves, tmp_path, monkeypatch):
    from favormap.mapfile import writer

    root, _ = maps
    src = tmp_path / "a.h5"
    src.write_bytes((root / "a.h5").read_bytes())
    before = _digest(src)
    put = writer.MapWriter.put

    def failing_put(self, name, data):
        if name == "tracks/xy":  # after the landmarks and frames were written
            raise OSError("disk full")
        return put(self, name, data)

    monkeypatch.setattr(writer.MapWriter, "put", failing_put)
    with pytest.raises(OSError, match="disk full"):
        extend_map(src, halves[2], tmp_path / "out.h5", ExtendConfig(max_landmarks=200))
    assert _digest(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5"]  # no output, no partial file


def test_transform_moves_the_new_poses_into_the_map_frame(maps, halves, tmp_path):
    from favormap.geometry import camera_centers, rotation_about

    root, s0 = maps
    _, a, b, _ = halves
    S = np.eye(4)  # map -> the new capture's own frame: scale 2, a rotation, a shift
    S[:3, :3] = 2.0 * rotation_about(np.array([0.3, 1.0, 0.2]), 0.7)
    S[:3, 3] = [1.0, -2.0, 0.5]
    b_other = moved_sequence(b, S)
    assert not np.allclose(b_other.frames[0].cam_from_world, b.frames[0].cam_from_world)
    s = extend_map(
        root / "a.h5",
        b_other,
        tmp_path / "out.h5",
        ExtendConfig(transform=np.linalg.inv(S).tolist()),
    )
    with Map.open(tmp_path / "out.h5") as m:
        np.testing.assert_allclose(
            camera_centers(m.cam_from_world[len(a) :]),
            camera_centers(np.stack([f.cam_from_world for f in b.frames])),
            atol=1e-6,
        )
        np.testing.assert_allclose(
            m.cam_from_world[len(a) :, :3, :3], np.stack([f.cam_from_world[:3, :3] for f in b.frames]), atol=1e-9
        )
    assert abs(s.landmarks_grown - s0.landmarks_grown) <= 0.05 * s0.landmarks_grown
    assert s.transform is not None


def _one_line_error(args, cwd: Path) -> str:
    r = subprocess.run(
        [sys.executable, "-m", "favormap", *map(str, args)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=240,
        cwd=cwd,
    )
    lines = r.stderr.strip().splitlines()
    assert r.returncode != 0 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert not (cwd / "out.h5").exists()
    return lines[0]


def test_bad_inputs_give_one_line_errors(maps, halves, tmp_path):
    root, _ = maps
    seq_root = halves[2].root
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "not found" in _one_line_error(["extend", tmp_path / "missing.h5", seq_root, "-o", "out.h5"], tmp_path)
    assert "sequence" in _one_line_error(["extend", root / "a.h5", empty, "-o", "out.h5"], tmp_path)
    assert "also an input" in _one_line_error(["extend", root / "a.h5", seq_root, "-o", root / "a.h5"], tmp_path)
    line = _one_line_error(["extend", root / "a.h5", seq_root, "-o", "out.h5", "--view-cone", "-3"], tmp_path)
    assert "view cone" in line
    line = _one_line_error(["extend", root / "a.h5", seq_root, "-o", "out.h5", "--max-landmarks", "0"], tmp_path)
    assert "max landmarks" in line
    line = _one_line_error(["extend", root / "a.h5", seq_root, "-o", "out.h5", "--align", "--transform", "x"], tmp_path)
    assert "exclude" in line


def test_cli_defaults_are_the_configs():
    import argparse

    from favormap.cli import make_parser

    sub = next(a for a in make_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["extend"]
    d = {a.dest: a.default for a in sub._actions}
    c = ExtendConfig()
    assert (d["view_cone"], d["match_radius"], d["min_similarity"], d["max_landmarks"]) == (
        c.view_cone_deg,
        c.match_radius_px,
        c.min_similarity,
        c.max_landmarks,
    )


def test_an_extension_keeps_each_frame_covered_as_a_build_would(halves, tmp_path):
    """Beyond the budget, every frame of the extended map, old or new, sees at least the map's
    min_frame_landmarks landmarks, or as many as the candidates allow (an extension that keeps them all):
    the landmarks a build's choice keeps among all the candidates."""
    from favormap.build import build_map, landmark_budget

    cfg = small_build_config(max_landmarks=50, min_frame_landmarks=500, voxel=_config().voxel)
    write_map(build_map(halves[1], cfg), tmp_path / "a.h5")
    s = extend_map(tmp_path / "a.h5", halves[2], tmp_path / "small.h5", ExtendConfig())
    extend_map(tmp_path / "a.h5", halves[2], tmp_path / "all.h5", ExtendConfig(max_landmarks=10**6))
    with Map.open(tmp_path / "small.h5") as ms, Map.open(tmp_path / "all.h5") as mall:
        n = ms.num_frames
        seen = np.bincount(ms.tracks()[1], minlength=n)
        tl, tf, _ = mall.tracks()
        allowed = np.bincount(tf, minlength=n)
        assert s.landmarks_after == len(ms) > 50 and s.landmarks_added > 0
        assert (seen >= np.minimum(500, allowed)).all() and (seen < allowed).any()
        keep, _ = landmark_budget(mall.track_length, mall.reproj_error, tl, tf, 50, 500)

        # new landmarks get fresh ids in each extension: compare positions
        def where(m, rows):
            return {tuple(p) for p in np.round(np.asarray(m.positions)[rows], 5).tolist()}

        assert where(mall, np.flatnonzero(keep)) == where(ms, np.arange(len(ms)))


def test_extending_a_map_of_refined_poses_warns_that_the_new_poses_are_used_as_given(maps, halves, tmp_path):
    """A map built with --refine-poses holds poses fitted to its images; the new frames' poses are taken as
    given, and the summary says so."""
    root, _ = maps
    with Map.open(root / "a.h5") as ma:
        m = ma.load()
    m.provenance = {**m.provenance, "config": {**m.provenance["config"], "refine_poses": True}}
    write_map(m, tmp_path / "refined.h5")
    s = extend_map(tmp_path / "refined.h5", halves[2], tmp_path / "out.h5", ExtendConfig(max_landmarks=200))
    assert len(s.warnings) == 1 and "refined by bundle adjustment" in s.warnings[0]
