"""Failure safety of map writing, and concurrent readers.

* atomic_path: temporary ``.NAME.XXXXXXXX.partial`` beside the target, removed on error, renamed
  over the target on success (fsynced), normal file mode;
* a real ``favormap build`` killed with SIGKILL at random moments (and exactly while it writes
  the map) never leaves anything at the target path but the old map, nothing, or a complete valid
  map; ``favormap info`` never succeeds on a partial file;
* several reader processes open and read the same map at once (HDF5 file locking is off), also
  while a writer keeps replacing it atomically.
"""

from __future__ import annotations

import hashlib
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_mapfile import random_map

from favormap.errors import FavormapError, MapFormatError
from favormap.mapfile import Map, atomic_path, write_map
from favormap.mapfile.validate import validate

ENV = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONUNBUFFERED": "1"}
PARTIAL = re.compile(r"^\.(?P<name>.+)\.[A-Za-z0-9_]+\.partial$")


def favormap(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "favormap", *map(str, args)], capture_output=True, text=True, timeout=timeout, env=ENV
    )


def leftovers(folder: Path, target: Path) -> list[Path]:
    """Everything in ``folder`` besides ``target``; fails on anything but hidden partial files of it."""
    out = []
    for p in folder.iterdir():
        if p == target:
            continue
        m = PARTIAL.match(p.name)
        assert m and m["name"] == target.name, f"unexpected file {p.name}"
        out.append(p)
    return out


# -- atomic_path -------------------------------------------------------------------------------------
def test_atomic_path_names_syncs_and_renames(tmp_path):
    target = tmp_path / "out.h5"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and PARTIAL.match(tmp.name) and PARTIAL.match(tmp.name)["name"] == "out.h5"
        assert not target.exists()
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and leftovers(tmp_path, target) == []
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_atomic_path_keeps_the_old_file_on_error(tmp_path):
    target = tmp_path / "out.h5"
    target.write_bytes(b"old")
    os.chmod(target, 0o640)
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_path(target) as tmp:
                tmp.write_bytes(b"half")
                raise exc
        assert target.read_bytes() == b"old" and leftovers(tmp_path, target) == []
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"new")
    assert target.read_bytes() == b"new" and target.stat().st_mode & 0o777 == 0o640  # mode of the replaced file kept


def test_atomic_path_refuses_bad_targets(tmp_path):
    with pytest.raises(FavormapError, match="is a directory"):
        with atomic_path(tmp_path):
            pass
    with pytest.raises(FavormapError, match="does not exist"):
        with atomic_path(tmp_path / "nope" / "x.h5"):
            pass
    assert list(tmp_path.iterdir()) == []


def test_write_map_failure_leaves_old_map_intact(tmp_path, monkeypatch):
    target = tmp_path / "m.h5"
    write_map(random_map(1), target)
    before = target.read_bytes()
    from favormap.mapfile import writer

    def broken(w, arrays):
        w.f.create_dataset("landmarks/ids", data=np.arange(3))
        raise OSError("disk full")

    monkeypatch.setattr(writer, "_write_contents", broken)
    with pytest.raises(OSError, match="disk full"):
        write_map(random_map(2), target)
    assert target.read_bytes() == before and leftovers(tmp_path, target) == []


def test_partial_files_are_never_maps(tmp_path, monkeypatch):
    """The magic attribute is written last: a file interrupted before it is refused by the reader."""
    from favormap.mapfile import writer

    seen = {}
    real = writer._write_contents

    def spy(w, arrays):
        real(w, arrays)
        w.f.flush()
        seen["tmp"] = Path(w.f.filename)
        shutil.copyfile(w.f.filename, tmp_path / "snapshot.h5")  # the file as a kill here would leave it
        raise KeyboardInterrupt

    monkeypatch.setattr(writer, "_write_contents", spy)
    with pytest.raises(KeyboardInterrupt):
        write_map(random_map(3), tmp_path / "m.h5")
    assert not seen["tmp"].exists() and not (tmp_path / "m.h5").exists()
    with pytest.raises(MapFormatError, match="not a favormap map"):
        Map.open(tmp_path / "snapshot.h5")
    r = favormap("info", tmp_path / "snapshot.h5")
    assert r.returncode != 0 and "not a favormap map" in r.stderr


# -- killing a real build ------------------------------------------------------------------------------
BUILD_ARGS = ["--resize", "0", "--quality", "fast", "--iterations", "10"]  # Adam: a build long enough to kill
BUILD_ARGS += ["--max-landmarks", "100", "--max-keypoints", "512", "-q"]


@pytest.fixture(scope="module")
def kill_sequence(tmp_path_factory):
    from favormap.synthetic import write_sequence

    root = tmp_path_factory.mktemp("kill_seq")
    write_sequence(root, n_frames=10, width=240, height=180)
    return root


def build_and_kill(seq: Path, out: Path, at: float | None = None, on_partial: bool = False, delay: float = 0.0):
    """Run ``favormap build``; SIGKILL it ``at`` seconds after the start, or ``delay`` seconds after
    its temporary map file appears. Returns the exit code (-9: killed)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "favormap", "build", str(seq), "-o", str(out), *BUILD_ARGS],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    t0 = time.monotonic()
    try:
        while proc.poll() is None:
            if on_partial and any(PARTIAL.match(p.name) for p in out.parent.iterdir()):
                time.sleep(delay)
                proc.send_signal(signal.SIGKILL)
                break
            if at is not None and time.monotonic() - t0 >= at:
                proc.send_signal(signal.SIGKILL)
                break
            if time.monotonic() - t0 > 180:
                proc.kill()
                pytest.fail("build did not finish in 180 s")
            time.sleep(0.002)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode in (0, -signal.SIGKILL), err.decode(errors="replace")
    return proc.returncode


def check_after(out: Path, rc: int, old: bytes | None) -> str:
    """The target is the old map, absent, or a complete valid map; info agrees. Returns the case."""
    parts = leftovers(out.parent, out)
    for p in parts:  # a stray partial is hidden; if it opens at all it is complete
        try:
            Map.open(p).close()
            assert validate(p).valid
        except MapFormatError:
            pass
    info = favormap("info", out)
    if not out.exists():
        assert rc != 0 and old is None
        assert info.returncode != 0 and "not found" in info.stderr
        return "absent"
    data = out.read_bytes()
    if old is not None and data == old:
        assert rc != 0
        assert info.returncode == 0
        return "old kept"
    r = validate(out)
    assert r.valid, r.problems
    assert info.returncode == 0 and "landmarks" in info.stdout
    return "new complete"


def test_killed_build_never_leaves_a_partial_map(kill_sequence, tmp_path):
    rng = random.Random(int(os.environ.get("FAVORMAP_KILL_SEED", "20240611")))
    old_map = tmp_path / "old.h5"
    write_map(random_map(4), old_map)
    old = old_map.read_bytes()
    cases = []
    # (kill time or None, kill when the temporary map appears, delay after it appears, pre-existing map)
    runs = [
        (rng.uniform(0.3, 2.0), False, 0.0, False),
        (rng.uniform(2.0, 6.0), False, 0.0, True),
        (None, True, rng.uniform(0.0, 0.02), True),  # while the map is being written
        (None, False, 0.0, True),
    ]  # runs to completion and replaces the old map
    for i, (at, on_partial, delay, pre) in enumerate(runs):
        folder = tmp_path / f"run{i}"
        folder.mkdir()
        out = folder / "out.h5"
        if pre:
            shutil.copyfile(old_map, out)
        rc = build_and_kill(kill_sequence, out, at=at, on_partial=on_partial, delay=delay)
        case = check_after(out, rc, old if pre else None)
        cases.append((at, on_partial, pre, rc, case))
    assert cases[-1][3] == 0 and cases[-1][4] == "new complete", cases
    assert any(c[3] == -signal.SIGKILL and c[1] for c in cases), cases  # a kill landed during the write
    assert any(c[4] == "old kept" for c in cases), cases


# -- concurrent readers -----------------------------------------------------------------------------
READER = r"""
import hashlib, sys, time
import numpy as np
from favormap.mapfile import Map
path, seconds, allowed = sys.argv[1], float(sys.argv[2]), set(sys.argv[3].split(","))
rng = np.random.default_rng(int(sys.argv[4]))
n, t0 = 0, time.monotonic()
while n < 3 or time.monotonic() - t0 < seconds:
    with Map.open(path, cache_size=8) as m:
        rows = rng.permutation(len(m))
        d, s = m.voxels(rows)
        order = np.argsort(rows)
        h = hashlib.sha256(m.ids.tobytes() + d[order].tobytes() + s[order].tobytes()).hexdigest()[:16]
        assert h in allowed, (h, allowed)
        m.tracks()
    n += 1
print(n)
"""


def _digest(path) -> str:
    with Map.open(path) as m:
        d, s = m.voxels(np.arange(len(m)))
        return hashlib.sha256(m.ids.tobytes() + d.tobytes() + s.tobytes()).hexdigest()[:16]


def _readers(path, allowed, n=4, seconds=1.5):
    return [
        subprocess.Popen(
            [sys.executable, "-c", READER, str(path), str(seconds), ",".join(allowed), str(i)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        for i in range(n)
    ]


def _finish(procs):
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-2000:]
        assert int(out.strip()) >= 3


def test_concurrent_readers(tmp_path):
    path = tmp_path / "shared.h5"
    write_map(random_map(6, L=60), path)
    _finish(_readers(path, {_digest(path)}))


def test_concurrent_readers_while_the_map_is_replaced(tmp_path):
    """Readers that (re)open the path while a writer replaces it always see a complete map."""
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    write_map(random_map(7, L=40), a)
    write_map(random_map(8, L=50), b)
    path = tmp_path / "shared.h5"
    shutil.copyfile(a, path)
    procs = _readers(path, {_digest(a), _digest(b)}, seconds=2.0)
    src = [random_map(7, L=40), random_map(8, L=50)]
    # random_map is deterministic per seed: each rewrite has the content of a.h5 or b.h5
    deadline = time.monotonic() + 2.0
    i = 0
    while time.monotonic() < deadline and any(p.poll() is None for p in procs):
        write_map(src[i % 2], path)
        i += 1
    _finish(procs)
    assert i >= 2
    assert not [p for p in tmp_path.iterdir() if PARTIAL.match(p.name)]
    assert _digest(path) in {_digest(a), _digest(b)}
