"""Maps from images without poses: the synthetic room's frames posed by pycolmap (their poses withheld),
agreeing with the truth up to a similarity; a query localized against the map built on them; a video; the
clear error when nothing can be posed."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import small_build_config

import favormap as package
from favormap.geometry import camera_centers, move_poses, perturb_pose, pose_error, rotation_angle_deg, umeyama

ENV = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONUNBUFFERED": "1"}
ENV.pop("FAVORMAP_DEBUG", None)
# the subprocesses run the favormap under test, wherever they start
ENV["PYTHONPATH"] = os.pathsep.join(filter(None, [str(Path(package.__file__).parents[1]), ENV.get("PYTHONPATH")]))


def favormap(*args):
    return subprocess.run([sys.executable, "-m", "favormap", *map(str, args)], capture_output=True, text=True, env=ENV)


def truth_alignment(estimated, truth):
    """(S, centre residuals): the similarity taking the estimated camera centres onto the true ones."""
    ce, ct = camera_centers(estimated), camera_centers(truth)
    S = umeyama(ce, ct)
    return S, np.linalg.norm(ce @ S[:3, :3].T + S[:3, 3] - ct, axis=1)


@pytest.fixture(scope="module")
def sfm(small_sequence, tmp_path_factory):
    from favormap.io.sfm import SfmOptions, estimate_poses

    out = tmp_path_factory.mktemp("sfm") / "room.sfm"
    return estimate_poses(small_sequence.root / "images", out, SfmOptions(threads=2))


def test_estimated_poses_agree_with_the_truth_up_to_a_similarity(sfm, small_sequence):
    truth = {f.name.removeprefix("images/"): f.cam_from_world for f in small_sequence.frames}
    assert sfm.registered == sorted(truth) and sfm.unregistered == []
    assert sfm.matcher == "exhaustive" and sfm.mapper == "incremental" and sfm.num_models == 1
    assert 0 < sfm.mean_reprojection_error_px < 0.5
    est = np.stack([f.cam_from_world for f in sfm.sequence.frames])
    gt = np.stack([truth[f.name] for f in sfm.sequence.frames])
    S, residual = truth_alignment(est, gt)
    extent = np.ptp(camera_centers(gt), axis=0).max()
    assert residual.max() < 0.005 * extent, (residual, extent)
    # the rotations between the cameras (the similarity from the centres alone leaves a fraction of a degree
    # of the orientation free: the orbit is nearly flat)
    rel_est = np.einsum("nij,kj->nik", est[:, :3, :3], est[0, :3, :3])
    rel_gt = np.einsum("nij,kj->nik", gt[:, :3, :3], gt[0, :3, :3])
    turn = rotation_angle_deg(np.einsum("nij,nkj->nik", rel_est, rel_gt))
    assert turn.max() < 0.1, turn
    # the reconstruction is a COLMAP model favormap reads back, and says what was done
    from favormap.io.readers import colmap

    assert colmap.find_model(sfm.reconstruction_path.parent.parent) == sfm.reconstruction_path
    note = json.loads((sfm.reconstruction_path.parent.parent / "favormap-sfm.json").read_text())
    assert note["registered"] == len(truth) and note["units"] == "arbitrary"
    from favormap.io.sfm import read_result

    again = read_result(sfm.reconstruction_path.parent.parent)
    assert again.to_dict() == sfm.to_dict()
    np.testing.assert_allclose(np.stack([f.cam_from_world for f in again.sequence.frames]), est)


def test_query_localizes_against_the_map_of_unposed_images(sfm, small_sequence, tmp_path):
    from favormap.build import build_map
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import write_map
    from favormap.synthetic import make_room, random_views_near, render

    truth = {f.name.removeprefix("images/"): f.cam_from_world for f in small_sequence.frames}
    est = np.stack([f.cam_from_world for f in sfm.sequence.frames])
    S, _ = truth_alignment(est, np.stack([truth[f.name] for f in sfm.sequence.frames]))
    path = tmp_path / "room.h5"
    write_map(build_map(sfm.sequence, small_build_config()), path)
    scene = make_room(0)
    views = random_views_near(list(truth.values()), 3, seed=5, max_trans=0.1, max_rot_deg=5.0, scene=scene)
    loc = Localizer(path, LocalizeConfig(iterations=3))
    rng = np.random.default_rng(0)
    errs = []
    for T in views:
        img = render(scene, small_sequence.cameras[0], T)[0]
        prior = move_poses(perturb_pose(T, 0.2, 8.0, rng), np.linalg.inv(S))  # the prior in the map's frame
        res = loc.localize(img, prior)
        assert res.success, res.message
        errs.append(pose_error(move_poses(res.cam_from_world, S), T))  # the result in the true frame
    errs = np.array(errs)
    # the room is ~4 units across, the cameras ~1.5 units from its walls
    assert np.median(errs[:, 0]) <= 0.01, errs
    # the similarity from the camera centres leaves a fraction of a degree of the map's orientation free (the
    # orbit is nearly flat), and pycolmap's threads make it vary from run to run (0.28-0.31 deg): the queries
    # must be turned no more than the map's own frames are under the same similarity (queries and frames agreed to
    # 0.01 deg over three reconstructions), and that free orientation stays a fraction of a degree
    frames_turn = np.median([pose_error(move_poses(e, S), truth[f.name])[1] for e, f in zip(est, sfm.sequence.frames)])
    assert np.median(errs[:, 1]) <= frames_turn + 0.02 and frames_turn <= 0.35, (errs, frames_turn)


def write_video(path, frames, repeat: int) -> None:
    """A Motion-JPEG video of ``frames``, each shown ``repeat`` times (a still camera between moves)."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    for im in frames:
        for _ in range(repeat):
            writer.write(im)
    writer.release()


def test_video_builds_a_map_in_arbitrary_units(small_sequence, tmp_path):
    video = tmp_path / "room.avi"
    frames = [cv2.imread(str(f.image_path)) for f in small_sequence.frames[:10]]
    write_video(video, frames, 2)
    out = tmp_path / "video.h5"
    args = ("--quality", "quick", "--max-keypoints", 1024, "--max-landmarks", 400, "--threads", 2, "--json")
    r = favormap("build", video, "-o", out, "--video-every", 2, *args)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["poses"]["registered"] == len(frames) and s["poses"]["matcher"] == "sequential"
    assert s["poses"]["units"] == "arbitrary" and s["frames"] == len(frames)
    assert (tmp_path / "video.h5.sfm" / "images" / "frame_000018.jpg").is_file()
    info = favormap("info", out)
    assert info.returncode == 0 and "units arbitrary" in info.stdout, info.stdout


def test_video_frames_by_motion_skip_a_still_camera(small_sequence, tmp_path):
    from favormap.io.video import extract_frames

    video = tmp_path / "still.avi"
    write_video(video, [cv2.imread(str(f.image_path)) for f in small_sequence.frames[:6]], 3)
    v = extract_frames(video, tmp_path / "frames", motion=0.01)
    assert v.frames_read == 18
    assert 2 <= len(v.names) <= 6 and all(n % 3 == 0 for n in v.frame_numbers), v.frame_numbers
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == v.names


def test_scale_multiplies_the_units(sfm, tmp_path):
    # one thread: COLMAP's result is then the same from run to run
    from favormap.io.sfm import SfmOptions, estimate_poses

    names = sfm.registered[:6]
    scaled = estimate_poses(sfm.image_dir, tmp_path / "s.sfm", SfmOptions(image_names=names, scale=2.5, threads=1))
    assert scaled.units == "scaled" and scaled.registered == names
    plain = estimate_poses(sfm.image_dir, tmp_path / "p.sfm", SfmOptions(image_names=names, threads=1))
    ratio = np.ptp(camera_centers(np.stack([f.cam_from_world for f in scaled.sequence.frames])), axis=0).max()
    ratio /= np.ptp(camera_centers(np.stack([f.cam_from_world for f in plain.sequence.frames])), axis=0).max()
    assert ratio == pytest.approx(2.5, rel=1e-3)


def test_nothing_registers_one_error_line_no_map(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):  # unrelated noise: no two images share a feature
        cv2.imwrite(str(photos / f"{i}.png"), rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    out = tmp_path / "map.h5"
    r = favormap("build", photos, "-o", out)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "no pose could be estimated for any of the 4 images" in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no map, no reconstruction, no leftovers


@pytest.mark.parametrize(
    "args, message",
    [
        (("--scale", "0"), "scale must be a positive number"),
        (("--video-every", "3"), "apply to a video"),
        (("--camera", "PINHOLE 10 10 5 5 5 5"), "the camera is 10x10 but the images are"),
    ],
)
def test_bad_options_of_unposed_images(small_sequence, tmp_path, args, message):
    r = favormap("build", small_sequence.root / "images", "-o", tmp_path / "m.h5", *args)
    assert r.returncode != 0 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_sfm_options_on_a_posed_sequence_are_refused(small_sequence, tmp_path):
    r = favormap("build", small_sequence.root, "-o", tmp_path / "m.h5", "--scale", "2")
    assert r.returncode != 0 and "--scale applies to images without poses" in r.stderr, r.stderr


def test_extend_with_images_without_poses(small_map, small_sequence, tmp_path):
    from favormap.mapfile import Map
    from favormap.synthetic import make_room, random_views_near, render

    scene = make_room(0)
    poses = [f.cam_from_world for f in small_sequence.frames[4:11]]
    views = random_views_near(poses, 6, seed=3, max_trans=0.05, max_rot_deg=3.0, scene=scene)
    photos = tmp_path / "photos"
    photos.mkdir()
    for i, T in enumerate(views):
        rgb = render(scene, small_sequence.cameras[0], T)[0]
        cv2.imwrite(str(photos / f"new{i}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    _, path = small_map
    out = tmp_path / "bigger.h5"
    r = favormap("extend", path, photos, "-o", out, "--threads", 2, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["frames_added"] == len(views) and s["poses"]["registered"] == len(views) and s["alignment"]
    assert (tmp_path / "bigger.h5.sfm" / "sparse" / "0").is_dir()
    with Map.open(out) as m:
        names = list(m.frame_names)
        added = {n: m.cam_from_world[names.index(n)] for n in names if n.startswith("new")}
    # the map's frame is the true one (exact poses): the new frames' poses, moved into it, are the true poses up
    # to the alignment of six frames' landmarks with the map's (~1 cm in a room ~4 units across)
    errs = np.array([pose_error(added[f"new{i}.png"], T) for i, T in enumerate(views)])
    assert np.median(errs[:, 0]) < 0.03 and np.median(errs[:, 1]) < 0.5, errs


ANCHORS = (0, 5, 10, 15)  # four frames spread along the orbit


def write_anchors(path, poses: dict) -> Path:
    """An anchor-poses file: a line 'NAME tx ty tz qx qy qz qw' (world_from_cam) per image."""
    from favormap.io.posefile import format_pose_tum

    path.write_text("# name tx ty tz qx qy qz qw\n" + "".join(f"{n} {format_pose_tum(T)}\n" for n, T in poses.items()))
    return path


def true_poses(small_sequence) -> dict:
    return {f.name.removeprefix("images/"): f.cam_from_world for f in small_sequence.frames}


def test_anchor_poses_put_the_reconstruction_in_their_frame_and_units(sfm, small_sequence):
    import pycolmap

    from favormap.io.sfm import sequence_from_reconstruction
    from favormap.io.sfm_anchors import anchor_reconstruction

    truth = true_poses(small_sequence)
    names = sorted(truth)
    rec = pycolmap.Reconstruction(str(sfm.reconstruction_path))
    fit = anchor_reconstruction(rec, {names[i]: truth[names[i]] for i in ANCHORS} | {"ghost.png": np.eye(4)})
    assert fit.used == [names[i] for i in ANCHORS] and fit.unregistered == ["ghost.png"]
    assert fit.rms < 0.002 and fit.max < 0.005 and fit.rotation_median_deg < 0.5, fit
    # every frame, not just the anchors, lands on its true pose within 5 mm (the room is ~4 units across: think
    # metres) and half a degree (the orientations COLMAP estimates differ from the truth by ~0.3 degrees)
    frames = sequence_from_reconstruction(rec, Path()).frames
    errs = np.array([pose_error(f.cam_from_world, truth[f.name]) for f in frames])
    assert len(errs) == len(truth) and errs[:, 0].max() < 0.005 and errs[:, 1].max() < 0.5, errs
    again = pycolmap.Reconstruction(str(sfm.reconstruction_path))
    with pytest.raises(Exception, match="need 3 images at least that registered, found 2.*not registered: ghost"):
        anchor_reconstruction(again, {names[0]: truth[names[0]], names[9]: truth[names[9]], "ghost.png": np.eye(4)})


def test_build_with_anchor_poses_is_metric(small_sequence, tmp_path):
    truth = true_poses(small_sequence)
    names = sorted(truth)
    anchors = write_anchors(tmp_path / "anchors.txt", {names[i]: truth[names[i]] for i in ANCHORS})
    with anchors.open("a") as f:
        f.write(f"nosuch.png {' '.join(['0'] * 6)} 1\n")
    out = tmp_path / "anchored.h5"
    args = ("--quality", "quick", "--max-keypoints", 1024, "--max-landmarks", 400, "--threads", 2, "--json")
    r = favormap("build", small_sequence.root / "images", "-o", out, "--anchor-poses", anchors, *args)
    assert r.returncode == 0, r.stderr
    p = json.loads(r.stdout)["poses"]
    a = p["anchors"]
    assert p["units"] == "anchors" and a["anchors"] == 4 and a["missing"] == ["nosuch.png"], p
    assert a["residual_rms"] < 0.002 and a["residual_max"] < 0.005 and a["rotation_median_deg"] < 0.5, a
    from favormap.mapfile import Map

    with Map.open(out) as m:
        errs = np.array([pose_error(T, truth[n]) for n, T in zip(m.frame_names, m.cam_from_world, strict=True)])
        assert m.provenance["poses"]["anchors"] == a
    assert len(errs) == len(truth) and errs[:, 0].max() < 0.005 and errs[:, 1].max() < 0.5, errs
    info = favormap("info", out)
    assert info.returncode == 0 and "units: metres, in the frame of 4 anchor poses" in info.stdout, info.stdout


def test_anchor_summary_names_the_anchors_not_used(capsys):
    from favormap.cli.build_sfm import print_anchors_summary

    fit = {"anchors": 3, "scale": 0.5, "residual_rms": 0.01, "residual_max": 0.02, "rotation_median_deg": 0.4}
    print_anchors_summary(fit | {"missing": ["a.png"], "unregistered": ["b.png", "c.png"]})
    lines = capsys.readouterr().out.splitlines()
    assert "3 images: scale 0.5" in lines[0] and "0.01 m RMS, 0.02 m max" in lines[0]
    assert lines[1:] == [
        "anchors not used    1 name no image: a.png",
        "anchors not used    2 not registered: b.png, c.png",
    ]


@pytest.mark.parametrize(
    "which, message",
    [
        ("two", "need 3 images at least, found 2"),
        ("missing", "need 3 images at least, found 2 (000000.png, 000005.png); naming no image: nosuch"),
        ("collinear", "lie on one line"),
        ("scale", "--anchor-poses and --scale exclude each other"),
    ],
)
def test_bad_anchor_poses_one_error_line_no_map(small_sequence, tmp_path, which, message):
    truth = true_poses(small_sequence)
    names = sorted(truth)
    poses = {names[i]: truth[names[i]] for i in ANCHORS[:2]}
    extra = ()
    if which == "missing":
        poses["nosuch"] = np.eye(4)
    if which == "collinear":
        poses[names[10]] = truth[names[10]].copy()
        for k, n in enumerate(poses):  # the same orientations, the centres 1 apart on the x axis
            poses[n] = np.eye(4)
            poses[n][:3, 3] = [-k, 0, 0]
    if which == "scale":
        poses[names[10]], extra = truth[names[10]], ("--scale", "2")
    anchors = write_anchors(tmp_path / "anchors.txt", poses)
    r = favormap("build", small_sequence.root / "images", "-o", tmp_path / "m.h5", "--anchor-poses", anchors, *extra)
    assert r.returncode != 0 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anchors.txt"]
