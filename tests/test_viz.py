"""rerun recordings: build, localize, eval and view write recordings that the rerun CLI accepts and
that hold the entity paths docs/rerun.md documents; no flag means no recording (and no rerun import);
a spawned viewer never collects analytics."""

from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from favormap.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "rerun.md"
_ENTITY = re.compile(r" - (/[^ ]+) - data columns")
_RERUN_ENV = {**os.environ, "CI": "1"}  # the rerun CLI then records no usage analytics at all


def _rerun_cli() -> list[str]:
    from favormap.viz.recording import rerun_executable

    exe = rerun_executable()
    return [exe] if exe else [sys.executable, "-m", "rerun"]


def _verify(rrd: Path) -> None:
    out = subprocess.run(
        _rerun_cli() + ["rrd", "verify", str(rrd)], capture_output=True, text=True, env=_RERUN_ENV, timeout=60
    )
    assert out.returncode == 0, out.stdout + out.stderr


def _entities(rrd: Path) -> set[str]:
    """Entity paths of the data recording (blueprint and property entities left out)."""
    out = subprocess.run(
        _rerun_cli() + ["rrd", "print", str(rrd)], capture_output=True, text=True, env=_RERUN_ENV, timeout=60
    )
    assert out.returncode == 0, out.stderr
    paths = set(_ENTITY.findall(out.stdout))
    assert "/viewport" in paths, "the recording carries no blueprint"
    return {
        p
        for p in paths
        if not p.startswith(("/view/", "/container/", "/viewport", "/time_panel", "/__", "/blueprint"))
        and p not in ("/top_panel", "/blueprint_panel", "/selection_panel")
    }


@pytest.fixture(autouse=True)
def _strict(monkeypatch):
    monkeypatch.setenv("FAVORMAP_RERUN_STRICT", "1")  # logging errors fail the test instead of a warning


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A 10-frame synthetic sequence, its map and the build recording."""
    from favormap.synthetic import write_sequence

    root = tmp_path_factory.mktemp("viz")
    seq = root / "seq"
    write_sequence(seq, n_frames=10, width=240, height=180)
    mp, rrd = root / "map.h5", root / "build.rrd"
    os.environ["FAVORMAP_RERUN_STRICT"] = "1"
    try:
        rc = main(
            [
                "build",
                str(seq),
                "-o",
                str(mp),
                "--resize",
                "0",
                "--quality",
                "fast",
                "--iterations",
                "30",
                "--max-landmarks",
                "200",
                "-q",
                "--rerun-save",
                str(rrd),
            ]
        )
    finally:
        os.environ.pop("FAVORMAP_RERUN_STRICT", None)
    assert rc == 0
    return root, seq, mp, rrd


def _documented() -> list[re.Pattern]:
    """Entity paths of the docs/rerun.md tables (first column, in backticks), `<x>` = one path part."""
    pats = []
    for line in DOCS.read_text().splitlines():
        m = re.match(r"\|\s*`(/?[^`]+)`\s*\|", line)
        if m and not m.group(1).startswith("--"):
            p = "/" + m.group(1).strip("/")
            pats.append(
                re.compile(
                    "^" + re.sub(r"<[^>]+>", "[^/]+", re.escape(p).replace(r"\<", "<").replace(r"\>", ">")) + "$"
                )
            )
    return pats


def _check_documented(paths: set[str]) -> None:
    pats = _documented()
    missing = sorted(p for p in paths if not any(r.match(p) for r in pats))
    assert not missing, f"entity paths missing from docs/rerun.md: {missing}"


# ---------------------------------------------------------------------------------------------
def test_no_flag_no_recording_and_no_rerun_import(tmp_path):
    from favormap.cli import make_parser
    from favormap.viz import recording_from_args

    for argv in (
        ["build", "seq", "-o", "m.h5"],
        ["localize", "m.h5", "q.png", "--prior", "p.txt"],
        ["eval", "m.h5", "seq"],
    ):
        args = make_parser().parse_args(argv)
        assert args.rerun is False and args.rerun_save is None and args.rerun_connect is None
        assert recording_from_args(args, "favormap test") is None
    assert recording_from_args(argparse.Namespace(), "favormap test") is None
    code = (
        "import sys; from favormap.cli import make_parser; from favormap.viz import recording_from_args; "
        "a = make_parser().parse_args(['build', 's', '-o', 'm.h5']); assert recording_from_args(a, 'x') is None; "
        "assert 'rerun' not in sys.modules, 'rerun imported without a flag'"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def test_build_recording(built):
    _, _, _, rrd = built
    _verify(rrd)
    paths = _entities(rrd)
    for p in (
        "/world",
        "/world/camera",
        "/world/camera/image",
        "/world/camera/image/keypoints",
        "/world/camera/image/tracks",
        "/world/camera/image/landmarks",
        "/world/map/landmarks",
        "/world/map/voxels",
        "/world/map/trajectory",
        "/world/map/trajectory/frustums",
        "/train/loss",
        "/train/psnr",
        "/build/timings",
        "/build/stats",
    ):
        assert p in paths, p
    _check_documented(paths)


def test_localize_recording(built):
    from favormap.geometry import inverse
    from favormap.io import read_sequence

    root, seq_dir, mp, _ = built
    seq = read_sequence(seq_dir)
    fr = seq.frames[4]
    pose = root / "prior.txt"
    np.savetxt(pose, inverse(fr.cam_from_world))
    rrd = root / "localize.rrd"
    assert main(["localize", str(mp), str(fr.image_path), "--prior", str(pose), "--rerun-save", str(rrd)]) == 0
    _verify(rrd)
    paths = _entities(rrd)
    for p in (
        "/world/map/landmarks",
        "/world/map/trajectory",
        "/world/query/prior",
        "/world/query/rendered/iterations",
        "/world/query/rendered/iterations/1",
        "/world/query/rendered/estimate",
        "/world/query/rendered/estimate/image",
        "/world/query/rendered/estimate/image/keypoints",
        "/world/query/rendered/estimate/image/inliers",
        "/world/query/rendered/estimate/image/guided",
        "/world/query/rendered/estimate/image/outliers",
        "/world/query/rendered/inliers",
        "/world/query/rendered/uncertainty",
        "/metrics/inliers/rendered",
        "/metrics/position_std/rendered",
        "/log/rendered",
    ):
        assert p in paths, p
    _check_documented(paths)


def test_eval_recording(built):
    root, seq_dir, mp, _ = built
    rrd = root / "eval.rrd"
    assert main(["eval", str(mp), str(seq_dir), "--every", "10", "--iters", "2", "-q", "--rerun-save", str(rrd)]) == 0
    _verify(rrd)
    paths = _entities(rrd)
    for p in (
        "/world/query/gt",
        "/world/query/prior",
        "/world/query/rendered/estimate/image",
        "/world/query/mean/estimate/image",
        "/metrics/translation_error/rendered",
        "/metrics/rotation_error_deg/mean",
        "/metrics/translation_error/prior",
    ):
        assert p in paths, p
    _check_documented(paths)


def test_view_recording(built):
    root, _, mp, _ = built
    rrd = root / "view.rrd"
    assert main(["view", str(mp), "--rerun-save", str(rrd)]) == 0
    _verify(rrd)
    paths = _entities(rrd)
    for p in (
        "/world",
        "/world/map/landmarks",
        "/world/map/voxels",
        "/world/map/trajectory",
        "/world/map/trajectory/frustums",
        "/map",
    ):
        assert p in paths, p
    _check_documented(paths)


def test_similarity_merge_and_prune_logging(built):
    """Per-match similarity (when the result carries ``match_similarity``) and the merge/prune
    helpers, through the Python API."""
    from favormap.io import read_rgb
    from favormap.localize.result import IterationResult, LocalizationResult
    from favormap.mapfile import Map
    from favormap.viz.recording import Recording

    root, seq_dir, mp, _ = built
    rrd = root / "api.rrd"
    with Map.open(mp) as m:
        T = m.cam_from_world[2]
        rows = np.arange(min(20, len(m)))
        from favormap.geometry import transform_points

        Xc = transform_points(T, m.positions[rows])
        cam = m.cameras[int(m.frame_camera_ids[0])]
        uv = Xc[:, :2] / Xc[:, 2:] * np.array(cam.focal) + np.array(cam.principal_point)
        res = LocalizationResult(
            True,
            T,
            len(rows),
            len(rows) - 3,
            [IterationResult(T, len(m), len(rows), len(rows) - 3, True)],
            {"extraction": 0.01},
            keypoints=uv.astype(np.float32),
            matches=np.c_[rows, np.arange(len(rows))],
            inlier_mask=np.arange(len(rows)) >= 3,
        )
        res.match_similarity = np.linspace(0.7, 1.0, len(rows))
        res.aligned = np.where((np.arange(len(rows)) % 2 == 0)[:, None], uv + 0.3, np.nan)  # LocalizeConfig.align
        with Recording("favormap test", kind="localize", save=rrd, map_=m, strict=True) as rec:
            rec.log_localization(0, read_rgb(seq_dir / "images" / "000002.png"), res, T, gt=T)
            rec.log_merge([mp, mp], mp)
            rec.log_prune(mp, mp)
    _verify(rrd)
    paths = _entities(rrd)
    for p in (
        "/world/query/rendered/estimate/image/similarity",
        "/world/query/rendered/estimate/image/aligned",
        "/metrics/similarity/rendered",
        "/world/map/sources",
        "/map/sources",
        "/world/removed",
        "/map/removed",
    ):
        assert p in paths, p
    _check_documented(paths)


def test_connect_streams_to_a_running_server(built):
    _, _, mp, _ = built
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    srv = subprocess.Popen(
        _rerun_cli() + ["--serve-grpc", "--port", str(port)],
        env=_RERUN_ENV,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        t_end = time.monotonic() + 20
        while time.monotonic() < t_end:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        else:
            pytest.skip("rerun --serve-grpc did not start")
        assert main(["view", str(mp), "--rerun-connect", f"rerun+http://127.0.0.1:{port}/proxy"]) == 0
    finally:
        srv.terminate()
        srv.wait(10)


def test_a_viewer_that_goes_away_while_closing_is_a_warning_not_an_error(tmp_path, capsys):
    """rerun raises from ``disconnect`` when the viewer it streamed to went away (seen with a spawned
    viewer that opened its port, then failed for want of a display, on a loaded machine): the
    recording reports that it was not delivered, and the command does not fail with a traceback."""
    from favormap.viz.recording import Recording

    rec = Recording("favormap test", save=tmp_path / "x.rrd", strict=False)

    def severed(*a, **kw):
        raise RuntimeError("gRPC connection severed: Failed to send messages")

    real = rec.rec.disconnect
    rec.rec.disconnect = severed
    assert rec.close() is False
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not fully delivered (gRPC connection severed" in err, err
    real()
    strict = Recording("favormap test", save=tmp_path / "y.rrd", strict=True)
    real = strict.rec.disconnect
    strict.rec.disconnect = severed
    with pytest.raises(RuntimeError, match="severed"):
        strict.close()
    real()


def test_spawned_viewer_collects_no_analytics(built, tmp_path):
    """Spawn a viewer with a fresh HOME and no display: it fails cleanly (one line, exit 1) and
    leaves no analytics config or queued events (without our CI=1 it would leave both)."""
    from favormap.viz import DEFAULT_PORT

    try:
        socket.create_connection(("127.0.0.1", DEFAULT_PORT), timeout=0.2).close()
        pytest.skip("something already listens on the default viewer port")
    except OSError:
        pass
    _, _, mp, _ = built
    env = {
        k: v
        for k, v in os.environ.items()
        if k
        not in (
            "CI",
            "DISPLAY",
            "WAYLAND_DISPLAY",
            "WAYLAND_SOCKET",
            "XDG_CONFIG_HOME",
            "XDG_DATA_HOME",
            "RERUN_ANALYTICS",
        )
    }
    env["HOME"] = str(tmp_path)
    out = subprocess.run(
        [sys.executable, "-m", "favormap", "view", str(mp)], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 1, out.stdout + out.stderr
    assert "rerun viewer could not start" in out.stderr
    assert not list(tmp_path.rglob("*")), [str(p) for p in tmp_path.rglob("*")]


def test_sequential_localize_recording_shows_the_refined_landmarks(built):
    import shutil

    from favormap.io import read_sequence

    root, seq_dir, mp, _ = built
    seq = read_sequence(seq_dir)
    folder = root / "stream"
    folder.mkdir(exist_ok=True)
    for k, fr in enumerate(seq.frames[2:6]):
        shutil.copy(fr.image_path, folder / f"{k:03d}{fr.image_path.suffix}")
    rrd = root / "stream.rrd"
    assert main(["localize", str(mp), str(folder), "--sequential", "--rerun-save", str(rrd)]) == 0
    _verify(rrd)
    paths = _entities(rrd)
    for p in ("/world/stream/refined", "/world/stream/refined/moves", "/metrics/refined_landmarks"):
        assert p in paths, p
    _check_documented(paths)
