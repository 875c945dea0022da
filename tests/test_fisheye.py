"""Fisheye camera models: the readers that carry them, the pinhole working camera and undistortion,
and the map file's working field of view."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pycolmap
import pytest

from favormap.io import Camera, read_sequence
from favormap.io.images import DEFAULT_MAX_FOV, prepare_image, working_camera
from favormap.io.posefile import read_camera

FISHEYE = {
    "SIMPLE_RADIAL_FISHEYE": [110.0, 80.0, 60.0, 0.03],
    "RADIAL_FISHEYE": [110.0, 80.0, 60.0, 0.03, -0.01],
    "OPENCV_FISHEYE": [112.0, 108.0, 81.0, 59.0, 0.03, -0.01, 0.002, 0.0],
    "FOV": [120.0, 118.0, 80.0, 60.0, 0.9],
}


# a 640x480 equidistant fisheye seeing 130 degrees across (f = 320 px / 65 deg), for the map-level tests
_F = 320 / np.radians(65)
WIDE_FISHEYE = Camera("OPENCV_FISHEYE", 640, 480, [_F, _F, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0])


def _image(path, w=160, h=120):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 255, (h, w, 3), np.uint8))


def _hfov(cam: Camera) -> float:
    return float(np.degrees(2 * np.arctan(cam.width / 2 / cam.focal[0])))


@pytest.mark.parametrize("model", sorted(FISHEYE))
@pytest.mark.parametrize("kind", ["text", "binary"])
def test_colmap_model_reads_fisheye(tmp_path, model, kind):
    params = FISHEYE[model]
    model_dir = tmp_path / "sparse" / "0"
    model_dir.mkdir(parents=True)
    _image(tmp_path / "images" / "a.png")
    (model_dir / "cameras.txt").write_text(f"1 {model} 160 120 {' '.join(map(str, params))}\n")
    (model_dir / "images.txt").write_text("1 1 0 0 0 0.5 -0.2 1.0 1 a.png\n\n")
    (model_dir / "points3D.txt").write_text("")
    if kind == "binary":  # written by COLMAP's own binary writer
        rec = pycolmap.Reconstruction(str(model_dir))
        for f in ("cameras.txt", "images.txt", "points3D.txt"):
            (model_dir / f).unlink()
        rec.write_binary(str(model_dir))
    seq = read_sequence(tmp_path)
    cam = seq.cameras[1]
    assert seq.format == "colmap" and cam.model == model and cam.is_fisheye
    np.testing.assert_allclose(cam.params, params)
    np.testing.assert_allclose(seq.frames[0].cam_from_world[:3, 3], [0.5, -0.2, 1.0])


def test_nerf_reads_and_writes_opencv_fisheye(tmp_path):
    from favormap.io.readers import nerf

    _image(tmp_path / "images" / "a.png")
    frame = {"file_path": "images/a.png", "transform_matrix": np.eye(4).tolist()}
    top = {"camera_model": "OPENCV_FISHEYE", "fl_x": 112.0, "fl_y": 108.0, "cx": 81.0, "cy": 59.0, "w": 160, "h": 120}
    top.update(k1=0.03, k2=-0.01, k3=0.002, k4=0.0005)
    (tmp_path / "transforms.json").write_text(json.dumps({**top, "frames": [frame]}))
    seq = read_sequence(tmp_path)
    cam = seq.cameras[0]
    assert cam.model == "OPENCV_FISHEYE"
    np.testing.assert_allclose(cam.params, [112, 108, 81, 59, 0.03, -0.01, 0.002, 0.0005])
    # instant-ngp's flag means the same model
    (tmp_path / "transforms.json").write_text(
        json.dumps({**top, "camera_model": None, "is_fisheye": True, "frames": [frame]})
    )
    assert read_sequence(tmp_path).cameras[0].model == "OPENCV_FISHEYE"
    # round trip through the writer
    nerf.write(seq, tmp_path)
    np.testing.assert_allclose(read_sequence(tmp_path).cameras[0].params, cam.params)
    # a fisheye has no pinhole field of view to take its focal length from
    (tmp_path / "transforms.json").write_text(
        json.dumps({"camera_model": "OPENCV_FISHEYE", "camera_angle_x": 2.0, "frames": [frame]})
    )
    with pytest.raises(Exception, match="needs fl_x"):
        read_sequence(tmp_path)


@pytest.mark.parametrize("model", sorted(FISHEYE))
def test_camera_line_reads_fisheye(model):
    line = f"{model} 160 120 {' '.join(map(str, FISHEYE[model]))}"
    cam = read_camera(line)
    assert cam.model == model
    np.testing.assert_allclose(cam.params, FISHEYE[model])


@pytest.mark.parametrize("model", sorted(FISHEYE))
def test_default_working_camera_sees_only_image(model):
    """The default working camera: centred, square pixels, every pixel inside the fisheye image, and
    no wider one would be (or the cap)."""
    cam = Camera(model, 160, 120, FISHEYE[model])
    wc = working_camera(cam, None)
    assert wc.model == "PINHOLE" and (wc.width, wc.height) == (160, 120)
    assert wc.focal[0] == wc.focal[1] and wc.principal_point == (80.0, 60.0)
    img = np.full((120, 160, 3), 255, np.uint8)
    out, _ = prepare_image(img, cam, None)
    assert out[1:-1, 1:-1].min() > 200  # no black border
    fov = _hfov(wc)
    if fov < DEFAULT_MAX_FOV - 1e-6:  # 1 % wider leaves some pixels without image content
        out, _ = prepare_image(img, cam.with_working_fov(fov * 1.01), None)
        assert (out < 250).any()


def test_undistortion_puts_points_where_the_pinhole_sees_them():
    """A world point's pixel in the fisheye image and in the working image are the same ray."""
    cam = Camera("OPENCV_FISHEYE", 320, 240, [150.0, 150.0, 161.0, 118.0, 0.04, -0.01, 0.0, 0.0])
    for fov in (None, 100.0):
        c = cam.with_working_fov(fov)
        wc = working_camera(c, 200)
        rays = np.array([[0.1, -0.05, 1.0], [-0.4, 0.3, 1.0], [0.6, 0.35, 1.0]])
        src = c.to_pycolmap().img_from_cam(rays)
        img = np.zeros((240, 320, 3), np.uint8)
        for u, v in src:
            cv2.circle(img, (int(u), int(v)), 3, (255, 255, 255), -1)
        out, wc2 = prepare_image(img, c, 200)
        np.testing.assert_allclose(wc2.K, wc.K)
        dst = (wc.K @ rays.T).T
        dst = dst[:, :2] / dst[:, 2:]
        for u, v in dst:
            assert out[int(v), int(u)].max() > 100, (fov, u, v)
    if fov is not None:
        assert abs(_hfov(wc) - fov) < 1e-9


def test_working_fov_validated_and_stored(tmp_path):
    from favormap.mapfile.writer import camera_arrays

    with pytest.raises(Exception, match="working field of view"):
        Camera("OPENCV_FISHEYE", 160, 120, FISHEYE["OPENCV_FISHEYE"], 180.0)
    cam = Camera("OPENCV_FISHEYE", 160, 120, FISHEYE["OPENCV_FISHEYE"], 90.0)
    assert Camera.from_dict(cam.to_dict()).working_fov == 90.0
    assert cam.scaled(80, 60).working_fov == 90.0
    a = camera_arrays({0: cam, 1: Camera("PINHOLE", 10, 10, [5, 5, 5, 5])})
    np.testing.assert_array_equal(a["cameras/working_fov"], [90.0, 0.0])
    assert "cameras/working_fov" not in camera_arrays({0: cam.with_working_fov(None)})


def test_fisheye_map_localizes_as_well_as_its_pinhole_working_camera(tmp_path):
    """Frames of a 640x480, 130 deg OPENCV_FISHEYE camera mapped at max_side 320 (larger than the working
    size, as real images scaled down for mapping are): a map of an orbit localizes held-out fisheye
    queries about as precisely as the map of the same orbit seen directly by its pinhole working
    camera, every query localized, median camera-centre error at most 1.2x the pinhole map's."""
    from conftest import localize_perturbed, small_build_config

    from favormap.build import build_map
    from favormap.localize import Localizer
    from favormap.mapfile import write_map
    from favormap.synthetic import camera_path, make_room, random_views_near, write_sequence

    fisheye = WIDE_FISHEYE
    pinhole = working_camera(fisheye, 320)
    poses = camera_path(12)
    queries = random_views_near(poses, 30, seed=3, max_trans=0.05, max_rot_deg=3.0, scene=make_room(0))
    config = small_build_config(max_side=320, iterations=40, max_landmarks=300)
    median = {}
    for name, cam in (("pinhole", pinhole), ("fisheye", fisheye)):
        path = tmp_path / f"{name}.h5"
        write_map(build_map(write_sequence(tmp_path / name, camera=cam, poses=poses), config), path)
        held_out = write_sequence(tmp_path / f"{name}_queries", camera=cam, poses=queries)
        median[name] = np.median(localize_perturbed(Localizer(path), held_out.frames)[:, 0])
    assert median["fisheye"] <= 1.2 * median["pinhole"], median


def test_fisheye_frames_larger_than_the_working_size_keep_their_sharpness():
    """A fisheye frame larger than the working size is undistorted at its own resolution and then
    shrunk. Its working image keeps well over half of the sharpness (variance of the Laplacian) of the
    same view rendered directly by the pinhole working camera with anti-aliasing; shrinking the frame
    first and undistorting the small image stretches the periphery and loses a good part of that."""
    from favormap.synthetic import camera_path, make_room
    from favormap.synthetic.render import render

    fisheye = WIDE_FISHEYE
    pinhole = working_camera(fisheye, 320)
    scene, pose = make_room(0), camera_path(12)[3]
    direct, _ = render(scene, pinhole, pose, with_depth=False)
    source, _ = render(scene, fisheye, pose, with_depth=False)
    undistorted, cam = prepare_image(source, fisheye, 320)
    np.testing.assert_allclose(cam.K, pinhole.K)

    def sharpness(img):
        lap = cv2.Laplacian(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32), cv2.CV_32F)
        return float(lap[8:-8, 8:-8].var())  # the border, black outside the fisheye's view, left out

    shrunk_first, _ = prepare_image(
        cv2.resize(source, (320, 240), interpolation=cv2.INTER_AREA), fisheye.scaled(320, 240), 320
    )
    assert sharpness(undistorted) >= 0.45 * sharpness(direct)
    assert sharpness(shrunk_first) <= 0.75 * sharpness(undistorted)
