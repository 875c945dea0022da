"""tools/read_map_standalone.py, the map format's reference reader in NumPy + h5py, against favormap's
renderers: on random grids of R = 3, 4, 5 (camera rays and arbitrary rays) and on a built map, every
rendered descriptor within a cosine of 1e-6; the reader imports neither favormap nor torch; the
worked example of docs/map-format.md is what it computes."""

from __future__ import annotations

import ast
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "read_map_standalone.py"
COS_TOL = 1e-6


def _load_tool():
    spec = importlib.util.spec_from_file_location("read_map_standalone", TOOL)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


rms = _load_tool()


def _assert_same_directions(got: np.ndarray, want: np.ndarray, opacity: np.ndarray | None = None):
    """Row by row cosine >= 1 - COS_TOL; rows favormap renders as zero (a missed box) are zero here
    too. With ``opacity``, rays below 1e-9 are left out of the cosine: there 1 - exp(-sigma delta)
    is a few float64 roundings, in favormap as here (its cosine was 0.99989 at an opacity of 3e-15)."""
    got, want = got.reshape(-1, got.shape[-1]), want.reshape(-1, want.shape[-1])
    ng, nw = np.linalg.norm(got, axis=1), np.linalg.norm(want, axis=1)
    zero = nw == 0
    assert not got[zero].any()
    check = ~zero if opacity is None else ~zero & (opacity.ravel() > 1e-9)
    cos = (got[check] * want[check]).sum(1) / (ng[check] * nw[check])
    assert check.sum() >= 0.3 * len(check)
    assert cos.min() >= 1 - COS_TOL, f"min cosine {cos.min():.9f}"


def _random_grids(R: int, seed: int, L: int = 40, C: int = 16):
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(L, R, R, R, C))
    # raw densities from transparent to opaque (softplus's both tails), varying across the grid
    dens = rng.normal(size=(L, R, R, R)) * rng.choice([0.5, 3.0, 30.0], size=(L, 1, 1, 1))
    centers = rng.normal(scale=0.5, size=(L, 3))
    sizes = rng.uniform(0.05, 0.5, size=L)
    return desc, dens, centers, sizes


@pytest.mark.parametrize("R", [3, 4, 5])
def test_random_grids_match_favormap_from_a_camera(R):
    torch = pytest.importorskip("torch")
    from favormap.voxels.render import render_from_camera as torch_render
    from favormap.voxels.render_numpy import render_from_camera_numpy

    desc, dens, centers, sizes = _random_grids(R, seed=R)
    cam = np.array([2.5, -1.5, 1.8])
    centers[0] = cam + [0.0, 0.0, -1.0]  # a ray along a coordinate axis
    centers[1], sizes[1] = cam + [0.01, -0.02, 0.015], 0.3  # the camera inside the box
    flat = (desc.reshape(len(desc), R**3, -1), dens.reshape(len(desc), R**3), centers, sizes)
    for n in (12, 16):
        got = rms.render_from_camera(desc, dens, centers, sizes, cam, n)
        want = torch_render(*(torch.from_numpy(a) for a in flat), torch.from_numpy(cam), n_samples=n).numpy()
        _assert_same_directions(got, want)
        _assert_same_directions(got, render_from_camera_numpy(*flat, cam, n_samples=n))
        # unnormalised too: the same descriptor, not only its direction
        raw = rms.render_from_camera(desc, dens, centers, sizes, cam, n, normalize=False)
        want_raw = render_from_camera_numpy(*flat, cam, n_samples=n, normalize=False)
        np.testing.assert_allclose(raw, want_raw, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("R", [3, 4, 5])
def test_random_grids_match_favormap_on_arbitrary_rays(R):
    """Training-style rays (origin and direction anywhere, some missing the box) against favormap's
    ray_stencils + render in float64."""
    torch = pytest.importorskip("torch")
    from favormap.voxels.render import ray_stencils, render, to_local

    desc, dens, centers, sizes = _random_grids(R, seed=10 + R, L=20)
    rng = np.random.default_rng(R)
    L, K = len(centers), 32
    origins = centers[:, None] + rng.normal(size=(L, K, 3)) * sizes[:, None, None] * 4
    dirs = centers[:, None] - origins + rng.normal(size=(L, K, 3)) * sizes[:, None, None] * 0.6
    got, opacity = rms.render_rays(desc, dens, centers, sizes, origins, dirs, 12, normalize=False)
    t = {k: torch.from_numpy(v) for k, v in dict(o=origins, d=dirs, c=centers, s=sizes).items()}
    st, delta, hit = ray_stencils(to_local(t["o"], t["c"], t["s"]), t["d"], R, 12)
    want, want_opacity = render(
        torch.from_numpy(desc.reshape(L, R**3, -1)), torch.from_numpy(dens.reshape(L, R**3)), st, delta, hit
    )
    assert 0 < hit.float().mean() < 1  # both kinds of rays are exercised
    _assert_same_directions(got, want.numpy(), opacity)
    np.testing.assert_allclose(got, want.numpy(), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(opacity, want_opacity.numpy(), rtol=1e-7, atol=1e-10)


def test_built_map_matches_favormap(small_map):
    from favormap.geometry import camera_centers
    from favormap.mapfile import Map
    from favormap.voxels.render_numpy import render_from_camera_numpy

    _, path = small_map
    m = rms.load_map(path)
    rows = np.arange(len(m.ids))
    desc, dens = rms.read_grids(path, rows)
    with Map.open(path) as fm:
        assert m.grid_resolution == fm.grid_resolution and m.render_samples == fm.render_samples
        np.testing.assert_array_equal(m.ids, fm.ids)
        fdesc, fdens = fm.voxels(rows)
        np.testing.assert_array_equal(desc.reshape(fdesc.shape), fdesc)
        centres = camera_centers(fm.cam_from_world)
        rng = np.random.default_rng(0)
        for cam in [*centres[[0, 7]], centres[3] + rng.normal(scale=0.3, size=3)]:
            got = rms.render_from_camera(desc, dens, m.positions, m.voxel_size, cam, m.render_samples)
            want = render_from_camera_numpy(fdesc, fdens, fm.positions, fm.voxel_size, cam, fm.render_samples)
            _assert_same_directions(got, want)


def test_worked_example_of_the_doc():
    """The numbers of docs/map-format.md's worked example are what the reader computes."""
    text = (REPO / "docs" / "map-format.md").read_text()
    example = text[text.index("### Worked example") :]
    R = 3
    desc, dens = np.zeros((1, R, R, R, 2)), np.zeros((1, R, R, R))
    for l_, (d, r) in enumerate([((1, 0), -2.0), ((0, 1), 1.0), ((1, 1), 3.0)]):
        desc[0, :, :, l_], dens[0, :, :, l_] = d, r
    c, o = np.array([[1.0, 2.0, 3.0]]), np.array([1.0, 2.0, 1.0])
    raw = rms.render_from_camera(desc, dens, c, [0.5], o, 4, normalize=False)[0]
    unit = rms.render_from_camera(desc, dens, c, [0.5], o, 4)[0]
    _, opacity = rms.render_rays(desc, dens, c, [0.5], o[None, None], (c - o)[:, None], 4)
    assert f"d̂ = ({raw[0]:.6f}, {raw[1]:.6f}), opacity A = {opacity[0, 0]:.6f}" in example
    assert f"**({unit[0]:.6f}, {unit[1]:.6f})**" in example
    # the per-sample table's weights sum to the opacity
    weights = [float(row.split("|")[7]) for row in re.findall(r"^\| \d \|.*$", example, re.M)]
    assert len(weights) == 4 and abs(sum(weights) - opacity[0, 0]) < 1e-5


def test_imports_only_numpy_h5py_and_the_standard_library(small_map):
    tree = ast.parse(TOOL.read_text())
    tops = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    tops |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 0}
    assert tops - set(sys.stdlib_module_names) == {"numpy", "h5py"}
    _, path = small_map
    code = (
        "import json, runpy, sys, io, contextlib\n"
        f"sys.argv = ['read_map_standalone.py', {str(path)!r}, '--landmark', '2', '--camera', '0', '0', '0']\n"
        "out = io.StringIO()\n"
        "with contextlib.redirect_stdout(out):\n"
        "    try:\n"
        f"        runpy.run_path({str(TOOL)!r}, run_name='__main__')\n"
        "    except SystemExit as e:\n"
        "        assert e.code == 0, e.code\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('favormap', 'torch'))\n"
        "print(json.dumps({'bad': bad, 'out': json.loads(out.getvalue())}))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd="/")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["bad"] == []
    assert res["out"]["landmarks"] == [2] and abs(np.linalg.norm(res["out"]["descriptors"][0]) - 1) < 1e-9


def test_cli_renders_and_refuses_bad_input(small_map, tmp_path):
    _, path = small_map
    run = lambda *a: subprocess.run([sys.executable, str(TOOL), *map(str, a)], capture_output=True, text=True)  # noqa: E731
    r = run(path, "--landmark", 1, "--origin", 0, 0, 0, "--direction", 0, 0, 1, "--raw")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    m = rms.load_map(path)
    d, dn = rms.read_grids(path, [1])
    want = rms.render_rays(
        d, dn, m.positions[[1]], m.voxel_size[[1]], [[[0, 0, 0]]], [[[0, 0, 1]]], m.render_samples, False
    )
    np.testing.assert_allclose(out["descriptors"][0], want[0][0, 0], rtol=1e-12, atol=1e-15)
    (tmp_path / "x.h5").write_bytes(b"not a map")
    for args in [(tmp_path / "x.h5", "--landmark", 0, "--camera", 0, 0, 0), (path, "--landmark", 0)]:
        r = run(*args)
        assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("error: ")
