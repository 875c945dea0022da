"""Mistakes caught before any image is read or any map is opened: outputs into missing or read-only
folders, outputs that are inputs, and a file given where a sequence folder is expected."""

from __future__ import annotations

import numpy as np
import pytest

from favormap.cli import main
from favormap.errors import SequenceError
from favormap.io import Camera, Frame, Sequence, read_sequence
from favormap.io.readers import favormap_layout

READ_ONLY = "/proc"  # a folder no one can create files in, root included


@pytest.fixture
def no_image_reads(monkeypatch):
    """Any image decode fails the test: the checks must come before the images are read."""
    import favormap.io.images as images

    def boom(*a, **k):
        raise AssertionError("an image was read before the output was checked")

    monkeypatch.setattr(images, "imread", boom)


@pytest.fixture
def tiny_seq(tmp_path):
    import cv2

    root = tmp_path / "seq"
    frames = []
    for i in range(2):
        p = root / "images" / f"{i}.png"
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), np.zeros((8, 8, 3), np.uint8))
        T = np.eye(4)
        T[0, 3] = i
        frames.append(Frame(f"images/{i}.png", p, 0, T))
    favormap_layout.write(Sequence(root, "favormap", {0: Camera("PINHOLE", 8, 8, [8, 8, 4, 4])}, frames), root)
    return root


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize(
    "where, message",
    [("missing/map.h5", "output folder does not exist"), (READ_ONLY + "/map.h5", "output folder is not writable")],
)
def test_build_output_folder_checked_first(tiny_seq, tmp_path, capsys, no_image_reads, where, message):
    out = where if where.startswith("/") else str(tmp_path / where)
    assert main(["build", str(tiny_seq), "-o", out, "-q"]) == 1
    assert message in _err(capsys)


@pytest.mark.parametrize("target", ["images/0.png", "sequence.json"])
def test_build_output_that_is_an_input(tiny_seq, capsys, no_image_reads, target):
    out = tiny_seq / target
    before = out.read_bytes()
    assert main(["build", str(tiny_seq), "-o", str(out), "-q"]) == 1
    assert "is also an input" in _err(capsys)
    assert out.read_bytes() == before


def test_build_output_same_as_given_descriptor_file(tiny_seq, capsys, no_image_reads):
    desc = tiny_seq / "sequence.json"
    assert main(["build", str(desc), "-o", str(desc), "-q"]) == 1
    assert "is also an input" in _err(capsys)


def test_localize_output_checked_before_the_map_is_opened(tiny_seq, tmp_path, capsys, no_image_reads):
    fake_map = tmp_path / "not_a_map.h5"
    fake_map.write_bytes(b"nothing")
    query = tiny_seq / "images" / "0.png"
    assert main(["localize", str(fake_map), str(query), "--output", str(tmp_path / "missing" / "est.txt")]) == 1
    assert "output folder does not exist" in _err(capsys)
    assert main(["localize", str(fake_map), str(query), "--output", READ_ONLY + "/est.txt"]) == 1
    assert "not writable" in _err(capsys)
    for same in (query, fake_map):
        assert main(["localize", str(fake_map), str(query), "--output", str(same)]) == 1
        assert "is also an input" in _err(capsys)
    assert (
        main(["localize", str(fake_map), str(tiny_seq / "images"), "--output", str(tiny_seq / "images" / "est.png")])
        == 1
    )
    assert "query image" in _err(capsys)


@pytest.mark.parametrize("cmd", ["prune", "merge", "export"])
def test_map_operations_refuse_writing_over_an_input(tmp_path, capsys, cmd):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.write_bytes(b"x")
    b.write_bytes(b"y")
    argv = {
        "prune": ["prune", str(a), "-o", str(a)],
        "merge": ["merge", str(a), str(b), "-o", str(b)],
        "export": ["export", str(a), "-o", str(tmp_path / "a.ply")],
    }[cmd]
    if cmd == "export":  # an export target that is the map itself cannot end in .ply: refuse via the suffix rule
        a_ply = tmp_path / "a.ply"
        a_ply.write_bytes(b"x")
        argv = ["export", str(a_ply), "-o", str(a_ply)]
    assert main(argv) == 1
    assert "is also an input" in _err(capsys)
    assert a.read_bytes() == b"x" and b.read_bytes() == b"y"


def test_a_file_is_named_as_given_not_as_its_folder(tiny_seq, capsys, no_image_reads):
    image = tiny_seq / "images" / "0.png"
    with pytest.raises(SequenceError, match=r"0\.png is a file, not a sequence"):
        read_sequence(image)
    assert main(["build", str(image), "-o", str(tiny_seq.parent / "m.h5"), "-q"]) == 1
    err = _err(capsys)
    assert str(image) in err and "not a sequence" in err
    stray = tiny_seq.parent / "notes.txt"
    stray.write_text("hello")
    with pytest.raises(SequenceError, match="notes.txt is a file"):
        read_sequence(stray)


def test_the_descriptor_file_may_stand_for_its_folder(tiny_seq, monkeypatch):
    seq = read_sequence(tiny_seq / "sequence.json")
    assert seq.root == tiny_seq and len(seq) == 2


def test_build_with_a_truncated_image_names_the_file(tiny_seq, tmp_path):
    """A corrupt or truncated image stops build with exit 1 and one line naming it; no decoder
    warning (libjpeg/libpng write to the C stderr) reaches the terminal."""
    import json
    import os
    import subprocess
    import sys

    import cv2

    img = tiny_seq / "images" / "1.jpg"
    ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (8, 8, 3), dtype=np.uint8))
    img.write_bytes(buf.tobytes()[: len(buf) // 2])
    data = json.loads((tiny_seq / "sequence.json").read_text())
    data["frames"][1]["image"] = "images/1.jpg"
    (tiny_seq / "sequence.json").write_text(json.dumps(data))
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "build", str(tiny_seq), "-o", str(tmp_path / "m.h5"), "-q"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "RERUN_ANALYTICS": "false"},
    )
    assert r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(img) in lines[0] and "truncated JPEG" in lines[0], r.stderr
    assert not (tmp_path / "m.h5").exists()


@pytest.mark.parametrize("field, value", [("match_window", 0), ("max_epipolar_px", 0.0)])
def test_build_map_refuses_a_tracking_config_before_reading_images(tiny_seq, no_image_reads, field, value):
    """The Python API checks the tracking settings up front, as the CLI checks its flags."""
    from dataclasses import replace

    from favormap.build import BuildConfig, build_map
    from favormap.errors import InputError

    with pytest.raises(InputError, match=field):
        build_map(read_sequence(tiny_seq), replace(BuildConfig(), **{field: value}))
