"""Mapping poses refined by bundle adjustment (favormap.pose_refinement) and the RANSAC threshold that
follows a map's measured pose noise (LocalizeConfig.ransac_threshold)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from conftest import small_build_config

from favormap.geometry import camera_centers, pose_error


def _perturbed(seq, deg: float, shift: float, seed: int = 0):
    """``seq`` with every pose turned by ``deg`` about a random axis through the camera centre and the
    centre moved by ``shift`` (units) in a random direction: the errors of motion capture, not of the
    images."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    frames = []
    for f in seq.frames:
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
        T = f.cam_from_world.copy()
        c = -T[:3, :3].T @ T[:3, 3] + shift * rng.normal(size=3) / np.sqrt(3)
        T[:3, :3] = turn @ T[:3, :3]
        T[:3, 3] = -T[:3, :3] @ c
        frames.append(dataclasses.replace(f, cam_from_world=T))
    return dataclasses.replace(seq, frames=frames)


def _errors(poses, truth):
    e = np.array([pose_error(a, b) for a, b in zip(poses, truth)])
    return np.median(e[:, 0]), np.median(e[:, 1])


@pytest.fixture(scope="module")
def noisy_stages(small_sequence):
    """The build's stages up to triangulation on the small room with poses off by 0.5 deg / 0.01 units."""
    from favormap.build import ExtractorSpec, extract_sequence, track_frames, triangulate_tracks

    cfg = small_build_config()
    ff = extract_sequence(small_sequence, ExtractorSpec("sift", cfg.max_keypoints), cfg.max_side)
    noisy = _perturbed(small_sequence, 0.5, 0.01)
    ff_noisy = dataclasses.replace(ff, cam_from_world=np.stack([f.cam_from_world for f in noisy.frames]))
    tracks_exact, tracks_noisy = track_frames(ff, cfg), track_frames(ff_noisy, cfg)
    return cfg, ff_noisy, tracks_exact, tracks_noisy, triangulate_tracks(tracks_noisy, ff_noisy, cfg)


def test_the_matches_say_when_the_poses_fit_the_images_less_well_than_the_keypoints(noisy_stages):
    """The right tracking matches lie within SIFT's keypoint precision of their epipolar lines under exact
    poses and beyond it under poses off by half a degree: the build summary suggests --refine-poses for the
    latter only."""
    from favormap.pose_refinement import poses_need_refinement

    _, _, tracks_exact, tracks_noisy, _ = noisy_stages
    assert tracks_exact.epipolar_median_px < 1.0 < tracks_noisy.epipolar_median_px
    assert not poses_need_refinement(tracks_exact.epipolar_median_px, 1.0)
    assert poses_need_refinement(tracks_noisy.epipolar_median_px, 1.0)
    assert not poses_need_refinement(float("nan"), 1.0)  # a limit given, not measured


def test_bundle_adjustment_brings_perturbed_poses_back_to_the_images(noisy_stages, small_sequence):
    """Poses turned by 0.5 deg and moved by 0.01 units: refined with the tracks, each camera centre held
    near its given position, they turn back most of the way, the landmarks triangulated again fit their
    observations better, and the map keeps the frame of the given poses (no drift of the centres)."""
    from favormap.build import refine_mapping_poses, triangulate_tracks

    cfg, ff_noisy, _, tracks_noisy, lms = noisy_stages
    truth = np.stack([f.cam_from_world for f in small_sequence.frames])
    ref = refine_mapping_poses(lms, ff_noisy, cfg, tracks_noisy.epipolar_median_px)
    t_before, r_before = _errors(ff_noisy.cam_from_world, truth)
    t_after, r_after = _errors(ref.cam_from_world, truth)
    assert r_after < 0.4 * r_before, (r_after, r_before)
    assert t_after < t_before, (t_after, t_before)
    assert ref.final_rms_px < 0.6 * ref.initial_rms_px
    assert ref.prior_sigma > 0 and np.median(ref.rotation_change_deg) > 0.2
    # the centres stay where they were given on average: the map keeps the world frame of the poses
    drift = np.linalg.norm(np.mean(camera_centers(ref.cam_from_world) - camera_centers(ff_noisy.cam_from_world), 0))
    assert drift < 0.01
    again = triangulate_tracks(tracks_noisy, dataclasses.replace(ff_noisy, cam_from_world=ref.cam_from_world), cfg)
    assert np.median(again.mean_reproj_error) < 0.7 * np.median(lms.mean_reproj_error)
    stats = ref.stats()
    assert stats["poses_refined"] and stats["pose_rotation_change_median_deg"] > 0.2


def test_a_map_built_with_refine_poses_stores_the_refined_ones(small_sequence, tmp_path, capsys):
    """build --refine-poses on poses off by 0.5 deg: the map holds the refined poses, closer to the truth
    than the given ones, and its build summary says how far they moved; without the flag the poses are
    stored as given and the summary suggests it."""
    from favormap.cli import main
    from favormap.mapfile import Map

    noisy = _perturbed(small_sequence, 0.5, 0.01)
    seq_dir = tmp_path / "noisy"
    shutil.copytree(small_sequence.root, seq_dir)
    meta = json.loads((seq_dir / "sequence.json").read_text())
    poses = {f.name: f.cam_from_world for f in noisy.frames}
    for fr in meta["frames"]:
        fr["cam_from_world"] = poses[fr["image"]].tolist()
    (seq_dir / "sequence.json").write_text(json.dumps(meta))
    truth = np.stack([f.cam_from_world for f in small_sequence.frames])
    given = np.stack([f.cam_from_world for f in noisy.frames])
    common = ["--max-keypoints", "1024", "--resize", "0", "--max-landmarks", "200", "--quality", "quick"]
    assert main(["build", str(seq_dir), "-o", str(tmp_path / "plain.h5"), *common]) == 0
    out = capsys.readouterr().out
    # turns drawn per frame share no rotation: the halves of the frames disagree on one, none is applied
    assert "--refine-poses fits them to the images" in out and "camera rotation     none applied" in out
    assert main(["build", str(seq_dir), "-o", str(tmp_path / "refined.h5"), "--refine-poses", *common]) == 0
    assert "poses refined" in capsys.readouterr().out
    with Map.open(tmp_path / "plain.h5") as plain, Map.open(tmp_path / "refined.h5") as refined:
        assert plain.provenance["stats"]["poses_refined"] is False
        np.testing.assert_allclose(plain.cam_from_world, given, atol=1e-9)
        assert plain.stored_cam_from_rig is None and not plain.provenance["stats"]["camera_rotation_applied"]
        assert refined.provenance["stats"]["poses_refined"] is True
        assert _errors(refined.cam_from_world, truth)[1] < 0.5 * _errors(given, truth)[1]


def test_the_ransac_threshold_follows_the_map_s_pose_noise(small_map, tmp_path):
    """LocalizeConfig.ransac_max_error_px None: 4 px, or 1.5 times the epipolar limit a map's build measured
    where that is larger; a number given is kept."""
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map

    cfg = LocalizeConfig()
    assert cfg.ransac_threshold(None) == 4.0
    assert cfg.ransac_threshold(1.05) == 4.0
    assert cfg.ransac_threshold(6.0) == pytest.approx(9.0)
    assert LocalizeConfig(ransac_max_error_px=3.0).ransac_threshold(6.0) == 3.0
    m, path = small_map
    assert Localizer(path).config.ransac_max_error_px == 4.0  # exact poses: a small limit
    stats = {**m.provenance.get("stats", {}), "max_epipolar_px": 6.0}
    noisy = dataclasses.replace(m, provenance={**m.provenance, "stats": stats})
    write_map(noisy, tmp_path / "noisy.h5")
    assert Localizer(tmp_path / "noisy.h5").config.ransac_max_error_px == pytest.approx(9.0)
    with pytest.raises(Exception, match="ransac_max_error_px"):
        LocalizeConfig(ransac_max_error_px=0.0)
    with pytest.raises(Exception, match="fit_max_error_px"):
        LocalizeConfig(fit_max_error_px=-1.0)


def test_the_reported_uncertainty_includes_the_map_s_own_pose_noise(small_map, small_sequence, tmp_path):
    """A map whose build measured its poses to fit the images to 3 px (the right matches' median epipolar
    distance) cannot localize a query better than that: the reported camera-centre spread is at least 3 px at
    the landmarks' depth, whatever the number of inliers; the map of exact poses reports less."""
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map

    m, path = small_map
    stats = {**m.provenance.get("stats", {}), "epipolar_median_px": 3.0}
    write_map(dataclasses.replace(m, provenance={**m.provenance, "stats": stats}), tmp_path / "noisy.h5")
    fr = small_sequence.frames[5]
    cfg = LocalizeConfig(ransac_max_error_px=4.0)
    exact = Localizer(path, cfg).localize(fr.image_path, fr.cam_from_world)
    loc = Localizer(tmp_path / "noisy.h5", cfg)
    noisy = loc.localize(fr.image_path, fr.cam_from_world)
    assert exact.success and noisy.success
    inl = noisy.matches[noisy.inlier_mask]
    T = noisy.cam_from_world
    depth = np.median(loc.positions[inl[:, 0]] @ T[2, :3] + T[2, 3])
    floor = 3.0 / noisy.camera.K[0, 0] * depth
    assert noisy.covariance.center_std.min() >= 0.99 * floor
    assert exact.covariance.center_std.max() < noisy.covariance.center_std.min()
    assert noisy.covariance.rotation_std_deg >= 0.99 * np.degrees(3.0 / noisy.camera.K[0, 0])
