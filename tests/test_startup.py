"""Start-up: each command imports only what it needs. Times are measured by
tools/bench_startup.py, not here; these tests check which heavy modules a command pulls in."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

HEAVY = ("torch", "open3d", "pycolmap", "cv2", "h5py", "scipy", "rerun", "trimesh", "numpy", "tqdm")


def loaded(argv: list[str], spatial: bool = False):
    """Heavy modules a command imports (and, with ``spatial``, also whether scipy.spatial; then the
    command's output is returned too)."""
    heavy = HEAVY + (("scipy.spatial",) if spatial else ())
    code = (
        "import sys\nfrom favormap.cli import main\ntry:\n    rc = main(sys.argv[1:])\nexcept SystemExit:\n    rc = 0\n"
        f"print('LOADED', ','.join(h for h in {heavy!r} if h in sys.modules))\nprint('RC', rc)"
    )
    r = subprocess.run(
        [sys.executable, "-c", code, *argv],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "RERUN_ANALYTICS": "false"},
    )
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("LOADED"))
    assert "Traceback" not in r.stderr, r.stderr
    mods = {m for m in line.split(" ", 1)[1].split(",") if m}
    return (mods, r.stdout) if spatial else mods


def test_help_imports_no_heavy_module():
    assert loaded(["--help"]) == set()
    assert loaded(["localize", "--help"]) == set()


@pytest.mark.parametrize("cmd", ["info", "validate"])
def test_map_reading_commands_import_neither_torch_nor_opencv(small_map, cmd):
    _, path = small_map
    mods = loaded([cmd, str(path)])
    assert "h5py" in mods  # it did read the map
    assert not mods & {"torch", "cv2", "open3d", "pycolmap", "rerun", "trimesh", "scipy"}, mods


def test_localize_of_a_sift_map_imports_neither_torch_nor_scipy_spatial(small_map, small_sequence, tmp_path):
    """On the CPU a SIFT map localizes with OpenCV, NumPy, h5py and pycolmap only: voxels render in
    NumPy (favormap.voxels.render_numpy), small maps are searched by a scan (favormap.visibility),
    and torch (~2 s to import), scipy.spatial (~0.5 s), Open3D and the writer stack stay out."""
    import numpy as np

    from favormap.geometry import inverse

    _, path = small_map
    fr = small_sequence.frames[3]
    prior = tmp_path / "prior.txt"
    np.savetxt(prior, inverse(fr.cam_from_world))
    mods, out = loaded(
        ["localize", str(path), str(fr.image_path), "--prior", str(prior), "--device", "cpu"], spatial=True
    )
    assert ": localized" in out, out[-500:]
    assert {"cv2", "h5py", "pycolmap"} <= mods
    assert not mods & {"torch", "scipy.spatial", "open3d", "rerun", "trimesh"}, mods


def test_a_sequential_localize_of_a_sift_map_stays_as_light(small_map, small_sequence, tmp_path):
    """The stream's priors and its landmark refinement (triangulation on the tracks) add no heavy
    module: no torch, no scipy."""
    import shutil

    _, path = small_map
    folder = tmp_path / "stream"
    folder.mkdir()
    for k, fr in enumerate(small_sequence.frames[3:6]):
        shutil.copy(fr.image_path, folder / f"{k:03d}{fr.image_path.suffix}")
    mods, out = loaded(["localize", str(path), str(folder), "--sequential", "--device", "cpu"], spatial=True)
    assert out.count(": localized") == 3, out[-500:]
    assert not mods & {"torch", "scipy", "scipy.spatial", "open3d", "rerun", "trimesh"}, mods


def test_auto_device_does_not_import_torch_without_a_gpu_driver():
    """``--device auto`` (the default) resolves to the CPU without importing torch where no GPU
    driver is installed; with a driver it asks torch."""
    code = (
        "import sys\nfrom favormap.cli.common import _gpu_driver_present, auto_device\n"
        "print(auto_device('auto'), _gpu_driver_present(), 'torch' in sys.modules)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    device, driver, torch_loaded = r.stdout.split()
    if driver == "False":
        assert (device, torch_loaded) == ("cpu", "False")
    else:
        assert torch_loaded == "True" and device in ("cpu", "cuda")
