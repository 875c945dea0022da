"""Query keypoints aligned to the mapping images through the landmark's local plane
(LocalizeConfig.align, favormap.localize.align)."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import SMALL, small_build_config


@pytest.fixture(scope="module")
def off_path_queries(small_sequence, tmp_path_factory):
    """Six views 10-30 degrees round the room's orbit beyond both ends of the mapping arc."""
    from favormap.geometry import inverse, rotation_about
    from favormap.synthetic import make_room, write_sequence

    scene = make_room(0)
    poses = [f.cam_from_world for f in small_sequence.frames]
    c = np.array([0.0, 0.55, 0.8])  # the orbit's centre (favormap.synthetic.paths)

    def about(T, deg):
        M = np.eye(4)
        M[:3, :3] = rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(deg))
        M[:3, 3] = c - M[:3, :3] @ c
        return inverse(M @ inverse(T))

    centre = [inverse(T)[:3, 3] - c for T in poses]
    sign = 1.0 if np.cross(centre[-2], centre[-1])[2] > 0 else -1.0
    q = [about(poses[-1], sign * d) for d in (10, 20, 30)] + [about(poses[0], -sign * d) for d in (10, 20, 30)]
    assert all(scene.camera_is_valid(inverse(T)[:3, 3]) for T in q)
    root = tmp_path_factory.mktemp("align_queries")
    return write_sequence(
        root, poses=q, width=SMALL["width"], height=SMALL["height"], fov_deg=SMALL["fov_deg"], scene=scene
    )


def _errors(path, queries, align):
    from favormap.geometry import perturb_pose, pose_error
    from favormap.localize import LocalizeConfig, Localizer

    loc = Localizer(path, LocalizeConfig(align=align))
    rng = np.random.default_rng(0)
    out = []
    for fr in queries.frames:
        res = loc.localize(fr.image_path, perturb_pose(fr.cam_from_world, 0.1, 5.0, rng))
        assert res.success, res.message
        out.append(pose_error(res.cam_from_world, fr.cam_from_world)[0])
    return np.array(out), res


def test_aligned_keypoints_localize_views_off_the_mapping_path_more_precisely(
    small_sequence, off_path_queries, tmp_path
):
    """On the synthetic room with exact poses, a map built for them (BuildConfig.exact_poses: its tracks
    aligned through the landmarks' planes, BuildConfig.refine_window 9, and its observations' pixels
    stored) localizes views 10-30 degrees off its path, by default, with the inliers' keypoints aligned
    to the mapping images, more precisely than with the detected keypoints (measured when written, with
    the mapping images: median 0.0015 -> 0.00057 units, every query better)."""
    import dataclasses

    from favormap.build import build_map
    from favormap.mapfile import Map, write_map

    cfg = dataclasses.replace(small_build_config(), exact_poses=True)
    assert (cfg.refine_window, cfg.align_patches) == (9, 20)
    path = tmp_path / "exact.h5"
    write_map(build_map(small_sequence, cfg), path)
    with Map(path) as m:
        assert m.has_track_patches and m.track_patch_radius == 20
    plain, res_plain = _errors(path, off_path_queries, align=False)
    assert res_plain.aligned is None and "align" not in res_plain.timings
    aligned, res = _errors(path, off_path_queries, align=None)  # the map's choice
    assert np.median(aligned) < 0.6 * np.median(plain), (aligned, plain)
    assert np.sum(aligned < plain) >= 5, (aligned, plain)
    assert res.timings["align"] > 0
    # the result keeps, by match, the keypoints the final refinement used: inliers only
    assert res.aligned.shape == res.matches.shape
    assert not np.isfinite(res.aligned[~res.inlier_mask]).any()
    assert np.isfinite(res.aligned[res.inlier_mask, 0]).mean() > 0.5


def test_alignment_moves_keypoints_to_the_surface_point_of_the_reference_view(small_map, off_path_queries):
    """PlaneAligner.align from the true pose, with each inlier's keypoint moved 1 px off: the aligned
    keypoint lies where the surface point under the landmark's projection in its reference frame
    projects into the query (found by ray casting the synthetic room), far closer than the detected one
    (measured when written, the query 20 degrees off the path: median 0.071 px against 0.231 px, 95 %
    of the inliers converged)."""
    from favormap.geometry import inverse, project
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.align import blurred_gray
    from favormap.synthetic import make_room
    from favormap.synthetic.render import _cast

    _, path = small_map
    loc = Localizer(path, LocalizeConfig(align=True))
    al = loc._aligner
    scene = make_room(0)
    fr = off_path_queries.frames[1]
    T = fr.cam_from_world
    res = loc.localize(fr.image_path, T)
    inl = res.matches[res.inlier_mask]
    rows, kp = inl[:, 0], res.keypoints[inl[:, 1]].astype(np.float64)
    img, cam = loc.prepare(fr.image_path)
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, 2 * np.pi, len(kp))
    off = np.stack([np.cos(ang), np.sin(ang)], 1)
    moved, ok = al.align(blurred_gray(img, al.config.sigma), cam.K, T, loc.positions, rows, kp + off)
    assert ok.mean() > 0.7
    # the truth: the ray of the landmark's projection in its reference frame, cast into the room
    ref = al.reference_frames(loc.positions, rows, inverse(T)[:3, 3])
    X = loc.positions[rows]
    truth = np.zeros((len(rows), 2))
    for f in np.unique(ref):
        s = ref == f
        Tf = np.asarray(loc.map.cam_from_world[f])
        uv = project(al.K[f], Tf, X[s])
        d = np.concatenate([(uv - al.K[f][:2, 2]) / al.K[f][[0, 1], [0, 1]], np.ones((s.sum(), 1))], 1) @ Tf[:3, :3]
        o = inverse(Tf)[:3, 3]
        t, _ = _cast(scene, np.concatenate([np.broadcast_to(o, d.shape), d], 1).astype(np.float32))
        truth[s] = project(cam.K, T, o + t[:, None] * d)
    e_aligned = np.linalg.norm(moved[ok] - truth[ok], axis=1)
    e_detected = np.linalg.norm(kp[ok] - truth[ok], axis=1)
    assert np.median(e_aligned) < 0.15, np.median(e_aligned)
    assert np.median(e_aligned) < 0.5 * np.median(e_detected), (np.median(e_aligned), np.median(e_detected))


def test_alignment_without_the_mapping_images_is_one_error_line(small_map, small_sequence, tmp_path):
    from favormap.errors import InputError
    from favormap.localize import LocalizeConfig, Localizer

    _, path = small_map
    with pytest.raises(InputError, match="does not exist"):
        Localizer(path, LocalizeConfig(align=True, align_images=str(tmp_path / "nowhere")))
    # a sequence without the map's frames
    partial = tmp_path / "partial"
    shutil.copytree(small_sequence.root, partial)
    import json

    meta = json.loads((partial / "sequence.json").read_text())
    meta["frames"] = meta["frames"][:3]
    (partial / "sequence.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="lack 13 of the map's 16 frames"):
        Localizer(path, LocalizeConfig(align=True, align_images=str(partial)))
    fr = small_sequence.frames[0]
    prior = tmp_path / "prior.txt"
    np.savetxt(prior, np.linalg.inv(fr.cam_from_world))
    for extra in (
        ["--align", "--mapping-images", str(tmp_path / "nowhere")],
        ["--mapping-images", str(partial)],
        ["--align-references", "3"],
        ["--align", "--align-references", "0"],
    ):
        p = subprocess.run(
            [
                sys.executable,
                "-m",
                "favormap",
                "localize",
                str(path),
                str(fr.image_path),
                "--prior",
                str(prior),
                *extra,
            ],
            capture_output=True,
            text=True,
        )
        assert p.returncode != 0 and "Traceback" not in p.stderr, p.stderr
        assert len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_the_cli_aligns_on_request_and_refuses_a_too_small_refine_window(small_map, small_sequence, tmp_path):
    """`favormap localize --align` localizes with the alignment (its time in the JSON timings);
    `favormap build --refine-window 2` is one error line and writes nothing."""
    import json

    _, path = small_map
    fr = small_sequence.frames[5]
    prior = tmp_path / "prior.txt"
    np.savetxt(prior, np.linalg.inv(fr.cam_from_world))
    cmd = [sys.executable, "-m", "favormap", "localize", str(path), str(fr.image_path), "--prior", str(prior)]
    p = subprocess.run([*cmd, "--align", "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["success"] and out["timings"]["align"] > 0 and out["num_aligned"] > 0
    p = subprocess.run([*cmd, "--align"], capture_output=True, text=True)
    assert p.returncode == 0 and f"{out['num_aligned']} of {out['num_inliers']} inlier keypoints aligned" in p.stdout
    # without --align on a map not built with --exact-poses, and with --no-align: no alignment
    for extra in ([], ["--no-align"]):
        p = subprocess.run([*cmd, *extra, "--json"], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        out = json.loads(p.stdout)
        assert out["success"] and "align" not in out["timings"] and "num_aligned" not in out
    out_map = tmp_path / "never.h5"
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "favormap",
            "build",
            str(small_sequence.root),
            "-o",
            str(out_map),
            "--refine-window",
            "2",
        ],
        capture_output=True,
        text=True,
    )
    assert p.returncode != 0 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "--refine-window" in p.stderr and not out_map.exists()


@pytest.fixture(scope="module")
def patch_map(small_sequence, tmp_path_factory):
    """(map path, sequence copy) of a map built with the observation patches (BuildConfig.align_patches)
    from a copy of the small sequence, which the tests may remove."""
    from favormap.build import build_map
    from favormap.io import read_sequence
    from favormap.mapfile import write_map

    root = tmp_path_factory.mktemp("patch_map")
    shutil.copytree(small_sequence.root, root / "seq")
    seq = read_sequence(root / "seq")
    path = root / "patches.h5"
    write_map(build_map(seq, small_build_config(align_patches=20)), path)
    return path, root / "seq"


def test_stored_patches_align_as_the_mapping_images_do(patch_map, off_path_queries):
    """A map that stores its observations' pixels (`build --align-patches 20`) aligns the inliers'
    keypoints without the mapping images, to the same positions as the images give, and the same poses
    where both align the same keypoints. Where a template's footprint in the mapping frame leaves the
    stored patch, the patches keep the detected keypoint: they align a subset of what the images align,
    never another position. On the synthetic scenes of favormap.synthetic: 235 / 157 / 137 keypoints aligned
    from the patches, 235 / 158 / 137 from the images; on the second query the one more alignment (a
    correct one: 0.48 px from the landmark's true projection, the detected keypoint 1.50 px) moves the
    pose from 0.00063 to 0.00144 units, a pose at the scene's noise floor; on the others the poses agree
    within 1e-6 units (3e-4 relative)."""
    from favormap.geometry import perturb_pose, pose_error
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import Map

    path, seq = patch_map
    with Map(path) as m:
        assert m.has_track_patches and m.track_patch_radius == 20
        lm, fr, xy = m.tracks()
        p = m.track_patches(np.arange(0, len(lm), 97))
    assert p.shape[1:] == (41, 41) and p.dtype == np.uint8
    a = Localizer(path, LocalizeConfig(align=True))
    b = Localizer(path, LocalizeConfig(align=True, align_images=str(seq)))
    assert a._aligner.from_patches and not b._aligner.from_patches
    rng = np.random.default_rng(0)
    same_sets = 0
    for q in off_path_queries.frames[::2]:
        T = perturb_pose(q.cam_from_world, 0.1, 5.0, rng)
        ra, rb = a.localize(q.image_path, T), b.localize(q.image_path, T)
        assert ra.success and rb.success
        fa, fb = np.isfinite(ra.aligned[:, 0]), np.isfinite(rb.aligned[:, 0])
        assert fb.sum() > 0.5 * ra.inlier_mask.sum()
        assert not (fa & ~fb).any(), "the patches aligned a keypoint the images did not"
        assert fa.sum() >= 0.95 * fb.sum(), (fa.sum(), fb.sum())
        np.testing.assert_allclose(ra.aligned[fa], rb.aligned[fa], atol=1e-3)
        if np.array_equal(fa, fb) and np.array_equal(ra.matches, rb.matches):
            same_sets += 1
            ea, eb = (pose_error(r.cam_from_world, q.cam_from_world)[0] for r in (ra, rb))
            assert abs(ea - eb) <= 1e-3 * eb + 1e-9, (ea, eb)
    assert same_sets >= 2
    assert a._aligner._images == {}  # no mapping image was read


def test_stored_patches_sample_as_the_blurred_frames_do(patch_map, small_sequence):
    """PlaneAligner's samples of the stored patches equal the samples of the blurred frame images
    (the build's sequence and the small sequence hold the same images) wherever they are defined,
    and they are defined wherever the point lies inside the patch less the blur's reach and inside
    the frame (measured when written: 98.9 % of the points, differences below 0.002 grey levels)."""
    from favormap.io import load_image
    from favormap.localize.align import PlaneAligner, blurred_gray, sample
    from favormap.mapfile import Map

    path, _ = patch_map
    with Map(path) as m:
        al = PlaneAligner(m)
        lm, fr, xy = m.tracks()
        rng = np.random.default_rng(0)
        obs = rng.choice(len(lm), 200, replace=False)
        uv = xy[obs][:, None, :] + rng.uniform(-12, 12, (200, 30, 2))  # within 20 - 4 (blur) - 1 of the centre
        got = al._patch_samples(obs, fr[obs], uv)
        want = np.full_like(got, np.nan)
        for f in np.unique(fr[obs]):
            s = fr[obs] == f
            frame = small_sequence.frames[f]
            img, _ = load_image(frame.image_path, small_sequence.cameras[frame.camera_id], m.max_side)
            want[s] = sample(blurred_gray(img, al.config.sigma), uv[s])
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
    assert np.isfinite(got).mean() > 0.95
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=0.01)


def test_a_map_with_patches_aligns_after_its_images_are_gone(patch_map, small_map, small_sequence, tmp_path):
    """`favormap localize --align` on a map with patches needs no folder (the one it was built from
    removed); prune keeps the kept observations' patches, merge keeps them where every map has them
    and drops them, with a warning, where one does not; `info` names them; a bad size is one line."""
    import json

    from favormap.mapfile import Map
    from favormap.ops.merge import merge_maps
    from favormap.ops.prune import prune_map

    path, seq = patch_map
    fr = read_frames(seq)[3]
    prior = tmp_path / "prior.txt"
    np.savetxt(prior, np.linalg.inv(fr.cam_from_world))
    image = tmp_path / "query.png"
    shutil.copy(fr.image_path, image)
    pruned, merged, mixed = tmp_path / "pruned.h5", tmp_path / "merged.h5", tmp_path / "mixed.h5"
    prune_map(path, pruned, max_landmarks=200)
    shutil.rmtree(seq)
    cmd = [sys.executable, "-m", "favormap", "localize", str(pruned), str(image), "--prior", str(prior)]
    p = subprocess.run([*cmd, "--align", "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["success"] and out["num_aligned"] > 0.5 * out["num_inliers"]
    with Map(path) as a, Map(pruned) as b:
        ids_a = {int(i): r for r, i in enumerate(a.ids)}
        la, fa, xa = a.tracks()
        lb, fb, xb = b.tracks()
        key_a = {(int(a.ids[l]), int(f)): o for o, (l, f) in enumerate(zip(la, fa))}
        rows = [key_a[(int(b.ids[l]), int(f))] for l, f in zip(lb, fb)]
        assert len(ids_a) == len(a) and len(lb) < len(la)
        np.testing.assert_array_equal(b.track_patches(), a.track_patches(np.array(rows)))
    res = merge_maps([path, pruned], merged)
    assert not any("patches" in w for w in res.warnings)
    res = merge_maps([path, small_map[1]], mixed)
    assert any("tracks/patch" in w for w in res.warnings)
    with Map(merged) as m, Map(mixed) as n:
        assert m.has_track_patches and len(m.track_patches()) == len(m.tracks()[0])
        assert not n.has_track_patches
    p = subprocess.run([sys.executable, "-m", "favormap", "info", str(pruned)], capture_output=True, text=True)
    assert p.returncode == 0 and "observation patches 41 x 41 px" in p.stdout
    bad = tmp_path / "never.h5"
    p = subprocess.run(
        [sys.executable, "-m", "favormap", "build", str(small_sequence.root), "-o", str(bad), "--align-patches", "65"],
        capture_output=True,
        text=True,
    )
    assert p.returncode != 0 and len(p.stderr.strip().splitlines()) == 1 and "--align-patches" in p.stderr
    assert not bad.exists()


def test_the_writer_refuses_patches_that_do_not_match_the_observations(small_map, tmp_path):
    import dataclasses

    from favormap.errors import MapFormatError
    from favormap.mapfile import write_map

    m, _ = small_map
    n = len(m.track_xy)
    with pytest.raises(MapFormatError, match="tracks/patch"):
        write_map(dataclasses.replace(m, track_patch=np.zeros((n - 1, 5, 5), np.uint8)), tmp_path / "a.h5")
    with pytest.raises(MapFormatError, match="tracks/patch"):
        write_map(dataclasses.replace(m, track_patch=np.zeros((n, 5, 7), np.uint8)), tmp_path / "b.h5")
    assert not (tmp_path / "a.h5").exists() and not (tmp_path / "b.h5").exists()
    # the streaming writer (merge, prune) refuses a non-square patch at put(), before the file exists
    from favormap.mapfile.writer import MapWriter, map_arrays, map_header

    arrays = {**map_arrays(m), "tracks/patch": np.zeros((n, 5, 7), np.uint8)}
    with pytest.raises(ValueError, match="does not match"):
        with MapWriter(tmp_path / "c.h5", map_header(m), m.num_landmarks, m.num_frames) as w:
            for name, a in arrays.items():
                w.put(name, a)
    assert not (tmp_path / "c.h5").exists()


def read_frames(root):
    from favormap.io import read_sequence

    return read_sequence(root).frames


def test_several_references_average_the_alignments_to_each(small_map, off_path_queries, tmp_path):
    """AlignConfig.references = 3: each inlier is aligned to its landmark's three mapping frames
    nearest in direction, each alone, and the converged alignments are averaged; the references are
    each landmark's observations ranked by the angle at the landmark, nearest first."""
    import dataclasses
    import json

    from favormap.geometry import camera_centers, inverse
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.localize.align import blurred_gray

    _, path = small_map
    loc = Localizer(path, LocalizeConfig(align=True, align_references=3))
    al = loc._aligner
    assert al.config.references == 3
    fr = off_path_queries.frames[1]
    T = fr.cam_from_world
    res = loc.localize(fr.image_path, T)
    inl = res.matches[res.inlier_mask]
    rows, kp = inl[:, 0], res.keypoints[inl[:, 1]].astype(np.float64)
    C = inverse(T)[:3, 3]
    ref = al.reference_observations(loc.positions, rows, C, 3)
    assert ref.shape == (len(rows), 3)
    np.testing.assert_array_equal(ref[:, 0], al.reference_observations(loc.positions, rows, C))
    # ranked by the angle at the landmark between the observing camera and the query's
    centers = camera_centers(np.asarray(loc.map.cam_from_world))
    has3 = (ref >= 0).all(1)
    assert has3.mean() > 0.9
    X = loc.positions[rows][has3]
    u = centers[al.obs_frame[ref[has3]]] - X[:, None]
    q = (C - X)[:, None]
    cos = np.sum(u * q, -1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(q, axis=-1)
    assert np.all(np.diff(cos, axis=1) <= 1e-12)

    img, cam = loc.prepare(fr.image_path)
    gray = blurred_gray(img, al.config.sigma)
    moved, ok = al.align(gray, cam.K, T, loc.positions, rows, kp)
    each = [al._align_pairs(gray, cam.K, T, loc.positions, rows, ref[:, j], kp) for j in range(3)]
    conv = np.stack([o for _, o in each], 1)
    expect = np.stack([m for m, _ in each], 1)
    expect = np.sum(np.where(conv[..., None], expect, 0), 1) / np.maximum(conv.sum(1), 1)[:, None]
    np.testing.assert_array_equal(ok, conv.any(1))
    np.testing.assert_allclose(moved[ok], expect[ok], atol=1e-9)
    np.testing.assert_array_equal(moved[~ok], kp[~ok])
    assert (conv.sum(1) >= 2).mean() > 0.5  # most inliers average several alignments
    # from the command line
    prior = tmp_path / "prior.txt"
    np.savetxt(prior, inverse(T))
    p = subprocess.run(
        [sys.executable, "-m", "favormap", "localize", str(path), str(fr.image_path), "--prior", str(prior)]
        + ["--align", "--align-references", "3", "--json"],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["success"] and out["num_aligned"] > 0.5 * out["num_inliers"], out
    # one reference: the nearest one alone, as before
    al1 = dataclasses.replace(al.config, references=1)
    al.config = al1
    m1, ok1 = al.align(gray, cam.K, T, loc.positions, rows, kp)
    np.testing.assert_array_equal(ok1, each[0][1])
    np.testing.assert_allclose(m1, np.where(ok1[:, None], each[0][0], kp))


def test_multichannel_bilinear_samples_are_each_channels_samples():
    """io.images.sample_bilinear of an (H, W, 3) image (the alignment samples the image and its two
    gradients in one lookup) equals each channel sampled alone, outside the image too (NaN in every channel)."""
    from favormap.io.images import sample_bilinear

    rng = np.random.default_rng(0)
    img = rng.random((40, 50, 3), dtype=np.float32)
    xy = np.concatenate([rng.uniform(0, 50, (200, 2)) * [1, 0.8], [[-3.0, 5.0], [55.0, 10.0], [10.0, 45.0]]])
    xy = xy.reshape(-1, 7, 2)
    for outside in (None, np.nan):
        both = sample_bilinear(img, xy, outside=outside)
        assert both.shape == (*xy.shape[:-1], 3)
        for c in range(3):
            np.testing.assert_array_equal(both[..., c], sample_bilinear(np.ascontiguousarray(img[..., c]), xy, outside))
    assert np.isnan(both.reshape(-1, 3)[-3:]).all()
