"""Words and numbers a user reads: one reprojection-error figure, prune's
reasons in words, conventions and units named in the outputs."""

from __future__ import annotations

import numpy as np

from favormap.cli import main
from favormap.geometry import inverse, perturb_pose


def test_build_and_info_print_the_same_reprojection_error(small_map, capsys):
    from favormap.cli.build import print_summary, summary
    from favormap.mapfile import Map

    m, path = small_map
    with Map.open(path) as mm:
        info = mm.info()
    assert m.provenance["stats"]["median_reproj_error_px"] == info["median_reproj_error_px"]
    print_summary(summary(m, path))
    build_line = next(ln for ln in capsys.readouterr().out.splitlines() if "reproj" in ln)
    assert main(["info", str(path)]) == 0
    info_line = next(ln for ln in capsys.readouterr().out.splitlines() if "reproj" in ln)
    assert build_line == info_line and "px" in info_line


def test_prune_says_what_was_removed_and_why_in_words(small_map, tmp_path, capsys):
    _, path = small_map
    assert main(["prune", str(path), "-o", str(tmp_path / "p.h5"), "--min-track", "12", "--max-landmarks", "50"]) == 0
    out = capsys.readouterr().out
    assert "seen in fewer than 12 frames (--min-track 12)" in out
    assert "over the budget of 50 landmarks" in out
    assert "min_track" not in out
    assert main(["prune", str(path), "-o", str(tmp_path / "q.h5"), "--min-track", "1000"]) == 1
    err = capsys.readouterr().err
    assert "seen in fewer than 1000 frames (--min-track 1000)" in err and "min_track" not in err


def test_localize_and_query_name_conventions_and_units(small_map, small_sequence, tmp_path, capsys):
    _, path = small_map
    fr = small_sequence.frames[5]
    pose = tmp_path / "prior.txt"
    np.savetxt(pose, inverse(perturb_pose(fr.cam_from_world, 0.05, 3.0, np.random.default_rng(0))))
    assert main(["localize", str(path), str(fr.image_path), "--prior", str(pose)]) == 0
    out = capsys.readouterr().out
    assert "cam_from_world: q_xyzw" in out and "world_from_cam: q_xyzw" in out
    assert "camera centre in world" in out and "scene units" in out and "timings (ms)" in out
    assert "uncertainty (1 sigma): camera centre (" in out and "scene units along x, y, z; rotation" in out
    assert "noise model fitted to the inliers: landmark position errors " in out and "x the map's variance" in out
    assert main(["query", str(path), "--near", "0", "0", "0", "--knn", "3"]) == 0
    out = capsys.readouterr().out
    assert "scene units" in out and "PSNR dB" in out


def test_eval_table_gives_units_in_every_header():
    from favormap.localize.evaluate import EvalReport, format_table

    summary = {
        "localized": 1,
        "queries": 1,
        "false_successes": 0,
        "median_translation": 0.01,
        "median_rotation_deg": 0.2,
        "p90_translation": 0.02,
        "mean_time_s": 0.2,
        "recall": {"0.05/5": 1.0},
        "per_iteration": [
            {"iteration": 1, "median_translation": 0.01, "median_rotation_deg": 0.2, "mean_inliers": 50.0}
        ],
    }
    text = format_table([EvalReport("rendered", [], 1, (), summary)])
    header = next(ln for ln in text.splitlines() if "median t" in ln)
    for col in ("median t (units)", "median R (deg)", "mean inliers (count)"):
        assert col in header
    assert "ms/query" in text and "units" in text.splitlines()[0] and "deg" in text.splitlines()[0]
