"""Every subcommand, given bad input, prints ONE clear line on stderr and exits non-zero: no
traceback, no progress-bar debris, no output file.

Runs real subprocesses (``python -m favormap ...``). The subcommands are discovered from
``favormap.cli.make_parser()``; each gets generic bad inputs for its positional arguments (missing
file, empty folder, text file, truncated map, garbage bytes, foreign HDF5, newer map version) and
non-numbers for its numeric options; ``build``, ``info`` and ``validate`` get specific cases too.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_mapfile import random_map

from favormap.cli import make_parser
from favormap.mapfile import write_map

ENV = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONUNBUFFERED": "1", "COLUMNS": "100"}
ENV.pop("FAVORMAP_DEBUG", None)
WORKERS = 3


def subparsers() -> dict[str, argparse.ArgumentParser]:
    p = make_parser()
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


COMMANDS = sorted(subparsers())


# -- inputs ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad_inputs")
    d = {}
    d["missing file"] = root / "missing" / "nothing.h5"
    (root / "missing").mkdir()
    d["empty folder"] = root / "empty"
    d["empty folder"].mkdir()
    (root / "text").mkdir()
    d["text file"] = root / "text" / "notes.h5"
    d["text file"].write_text("this is not a map\n")
    good = root / "good.h5"
    write_map(random_map(0), good)
    data = good.read_bytes()
    (root / "trunc").mkdir()
    d["truncated map"] = root / "trunc" / "map.h5"
    d["truncated map"].write_bytes(data[: len(data) // 2])
    (root / "garbage").mkdir()
    d["garbage bytes"] = root / "garbage" / "map.h5"
    d["garbage bytes"].write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    (root / "foreign").mkdir()
    d["foreign hdf5"] = root / "foreign" / "data.h5"
    with h5py.File(d["foreign hdf5"], "w") as f:
        f["x"] = np.arange(5)
    (root / "newer").mkdir()
    d["newer map version"] = root / "newer" / "map.h5"
    shutil.copyfile(good, d["newer map version"])
    with h5py.File(d["newer map version"], "r+") as f:
        f.attrs["format_version"] = 99
    good.unlink()
    return root, d


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """Small broken sequences for ``build``."""
    from favormap.synthetic import write_sequence

    root = tmp_path_factory.mktemp("bad_seqs")
    good = root / "good"
    write_sequence(good, n_frames=6, width=96, height=72)
    s = {"good": good}
    s["images missing"] = root / "missing_images"
    shutil.copytree(good, s["images missing"])
    for p in sorted((s["images missing"] / "images").iterdir())[1:4]:
        p.unlink()
    s["unreadable image"] = root / "garbage_image"
    shutil.copytree(good, s["unreadable image"])
    (s["unreadable image"] / "images" / "000002.png").write_bytes(b"\x89PNG garbage bytes, not an image" * 10)
    s["all images unreadable"] = root / "all_garbage"
    shutil.copytree(good, s["all images unreadable"])
    for p in (s["all images unreadable"] / "images").iterdir():
        p.write_bytes(b"garbage")
    s["broken transforms.json"] = root / "nerf_broken"
    s["broken transforms.json"].mkdir()
    (s["broken transforms.json"] / "transforms.json").write_text('{"camera_angle_x": 0.8, "frames": [')
    s["broken sequence.json"] = root / "fm_broken"
    shutil.copytree(good, s["broken sequence.json"])
    (s["broken sequence.json"] / "sequence.json").write_text(
        '{"format": "favormap-sequence", "cameras": {"0": {"model": "PINHOLE"}}, "frames": []}'
    )
    return s


# -- running ----------------------------------------------------------------------------------------
def tree(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def run_case(args: list, work: Path) -> list[str]:
    """Run ``favormap ARGS`` in the empty folder ``work``; the contract violations (empty: OK)."""
    work.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(
            [sys.executable, "-m", "favormap", *map(str, args)],
            cwd=work,
            capture_output=True,
            text=True,
            timeout=240,
            env=ENV,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired:
        return [f"timed out: favormap {' '.join(map(str, args))}"]
    bad = []
    lines = r.stderr.strip("\n").split("\n")
    if r.returncode == 0:
        bad.append("exit code 0")
    if "Traceback" in r.stderr or "Traceback" in r.stdout:
        bad.append("traceback")
    if len(lines) != 1 or not lines[0].strip() or "\r" in r.stderr:
        bad.append(f"stderr is not one line: {r.stderr[-600:]!r}")
    elif not lines[0].startswith("favormap"):
        bad.append(f"stderr line does not name favormap: {lines[0]!r}")
    created = tree(work)
    if created:
        bad.append(f"files created: {sorted(created)}")
    return [f"favormap {' '.join(map(str, args))}: {b}" for b in bad]


def run_cases(cases: dict[str, list], base: Path) -> list[str]:
    def one(item):
        i, (name, args) = item
        return [f"[{name}] {v}" for v in run_case(args, base / f"case{i}")]

    with ThreadPoolExecutor(WORKERS) as ex:
        return [v for vs in ex.map(one, enumerate(cases.items())) for v in vs]


def generic_cases(
    name: str, sp: argparse.ArgumentParser, inputs: dict[str, Path], out: str = "out.h5"
) -> dict[str, list]:
    """Bad paths for every positional (and required option), and non-numbers for numeric options."""
    positionals = [a for a in sp._actions if not a.option_strings]
    required = [a for a in sp._actions if a.option_strings and a.required]
    groups = [g for g in sp._mutually_exclusive_groups if g.required]

    def args_with(path):
        args = [name]
        for a in positionals:
            args += [path, path] if a.nargs in ("+", "*") else [path]
        for a in required:
            is_out = a.dest in ("output", "out") or "-o" in a.option_strings
            args += [a.option_strings[-1], out if is_out else path]
        for g in groups:
            a = next((a for a in g._group_actions if a.nargs is None and a.type is None), g._group_actions[0])
            args += [a.option_strings[-1]] + (
                [path] if a.nargs is None else ["1"] * (a.nargs if isinstance(a.nargs, int) else 1)
            )
        return args

    cases = {}
    if positionals:
        # every bad map variant reaches Map.open the same way: the full set for the cheap map
        # commands, three for the others (they import torch/open3d: seconds per run)
        kinds = (
            list(inputs)
            if name in ("info", "validate", "prune", "merge")
            else ["missing file", "empty folder", "truncated map"]
        )
        for what in kinds:
            cases[what] = args_with(inputs[what])
    numeric = [a for a in sp._actions if a.option_strings and a.type in (int, float) and a.nargs is None]
    for a in numeric[:2]:
        cases[f"{a.option_strings[-1]} not a number"] = args_with(inputs["truncated map"]) + [
            a.option_strings[-1],
            "abc",
        ]
    return cases


@pytest.mark.parametrize("command", COMMANDS)
def test_bad_inputs_give_one_line_and_no_output(command, inputs, tmp_path):
    root, paths = inputs
    before = tree(root)
    sp = subparsers()[command]
    cases = generic_cases(command, sp, paths)
    if not cases:
        pytest.skip(f"{command} has no positional or numeric arguments")
    problems = run_cases(cases, tmp_path)
    assert tree(root) == before, "files were created beside the inputs"
    assert not problems, "\n".join(problems)


def test_known_commands_are_registered():
    assert {"build", "info", "validate"} <= set(COMMANDS)


def test_unknown_command_and_option(tmp_path):
    problems = run_cases(
        {
            "unknown command": ["frobnicate"],
            "unknown option": ["info", "--frobnicate", "x.h5"],
            "missing argument": ["info"],
        },
        tmp_path,
    )
    assert not problems, "\n".join(problems)


def test_build_bad_sequences_and_arguments(sequences, tmp_path):
    s = sequences
    out = "out.h5"
    q = ["--resize", "0", "--quality", "fast", "--iterations", "2", "-q"]
    cases = {
        name: ["build", s[name], "-o", out, *q]
        for name in ("images missing", "unreadable image", "broken transforms.json", "broken sequence.json")
    }
    cases.update(
        {
            "unknown --format": ["build", s["good"], "-o", out, "--format", "bogus", *q],
            "negative iterations": ["build", s["good"], "-o", out, "--iterations", "-3", "-q"],
            "iterations, closed form": ["build", s["good"], "-o", out, "--iterations", "5", "-q"],
            "grid 1": ["build", s["good"], "-o", out, "--grid", "1", "-q"],
            "negative resize": ["build", s["good"], "-o", out, "--resize", "-1", "-q"],
            "match window 0": ["build", s["good"], "-o", out, "--match-window", "0", "-q"],
            "epipolar 0 px": ["build", s["good"], "-o", out, "--max-epipolar", "0", "-q"],
            "non-numeric patch": ["build", s["good"], "-o", out, "--patch", "seven", "-q"],
            "missing -o": ["build", s["good"], *q],
        }
    )
    problems = run_cases(cases, tmp_path)
    assert not problems, "\n".join(problems)


def test_validate_and_info_name_the_problem(inputs, tmp_path):
    _, paths = inputs
    expect = {
        "missing file": "not found",
        "empty folder": "directory",
        "text file": "not",
        "truncated map": "truncated",
        "foreign hdf5": "not a favormap map",
        "newer map version": "upgrade favormap",
    }
    for command in ("info", "validate"):
        for what, word in expect.items():
            r = subprocess.run(
                [sys.executable, "-m", "favormap", command, str(paths[what])],
                capture_output=True,
                text=True,
                env=ENV,
                timeout=120,
                cwd=tmp_path,
            )
            assert r.returncode != 0 and word in r.stderr, (command, what, r.stderr)
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "validate", "--json", str(paths["truncated map"])],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
        cwd=tmp_path,
    )
    rep = json.loads(r.stdout)
    assert r.returncode != 0 and rep["valid"] is False and rep["problems"] and len(r.stderr.strip().splitlines()) == 1


def test_validate_valid_map_exit_0(tmp_path):
    p = tmp_path / "ok.h5"
    write_map(random_map(3), p)
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "validate", str(p)], capture_output=True, text=True, env=ENV, timeout=120
    )
    assert r.returncode == 0 and ": valid" in r.stdout and r.stderr == ""
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "validate", "--json", str(p)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    rep = json.loads(r.stdout)
    assert r.returncode == 0 and rep["valid"] is True and rep["problems"] == [] and rep["format_version"] == 1


# -- a build's errors come first: no progress bar before an error, the output checked before the inputs ---
def test_build_progress_bars_do_not_precede_an_error(sequences, tmp_path):
    problems = run_cases(
        {
            "unreadable image, no -q": [
                "build",
                sequences["unreadable image"],
                "-o",
                "out.h5",
                "--resize",
                "0",
                "--quality",
                "fast",
                "--iterations",
                "2",
            ]
        },
        tmp_path,
    )
    assert not problems, "\n".join(problems)


def test_build_checks_the_output_before_working(sequences, tmp_path):
    """With an impossible output AND unreadable images, the output must be the error: it is checked first."""
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "favormap",
            "build",
            str(sequences["all images unreadable"]),
            "-o",
            "no_such_folder/out.h5",
            "--resize",
            "0",
            "-q",
        ],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=240,
        cwd=tmp_path,
    )
    assert r.returncode != 0 and "output folder does not exist" in r.stderr, r.stderr
