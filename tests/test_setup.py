"""Set-up, CI and installation: the README's commands, the project venv on a
system Python that refuses pip (PEP 668), the pytest summary line, the schema in a wheel."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S).group(1)
    return [ln.split("#", 1)[0].strip() for ln in block.strip().splitlines()]


def test_readme_starts_with_setup_test_demo_and_ci_runs_them():
    setup, test, demo = readme_commands()  # exactly three lines
    assert setup == "bash tools/setup.sh" and demo == "favormap demo"
    ci = [ln.strip() for ln in (REPO / ".ci" / "run").read_text().splitlines()]
    assert setup in ci and test in ci and ci.index(setup) < ci.index(test)


def _run_setup_dry(python: str, env_extra=None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}
    env.update({"PYTHON": python, "FAVORMAP_SETUP_DRY_RUN": "1", **(env_extra or {})})
    r = subprocess.run(["bash", str(REPO / "tools" / "setup.sh")], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def _externally_managed(python: str) -> bool:
    r = subprocess.run(
        [
            python,
            "-c",
            "import os, sysconfig; print(os.path.isfile(os.path.join("
            "sysconfig.get_path('stdlib'), 'EXTERNALLY-MANAGED')))",
        ],
        capture_output=True,
        text=True,
    )
    return r.stdout.strip() == "True"


def test_setup_uses_a_project_venv_only_where_pip_is_refused(tmp_path):
    # a Python that allows pip (this interpreter, when it is not marked PEP 668): installs into it
    if not _externally_managed(sys.executable) and sys.prefix == sys.base_prefix:
        out = _run_setup_dry(sys.executable)
        assert "setup: installing into /" in out and ".venv" not in out
    # an active venv: installs into it
    v = tmp_path / "v"
    venv.create(v, with_pip=False)
    assert "active virtual environment" in _run_setup_dry(str(v / "bin" / "python"))
    # a PEP 668 system Python (Debian 12's /usr/bin/python3 here): the project venv
    system = shutil.which("python3", path="/usr/bin")
    if system is None or not _externally_managed(system):
        pytest.skip("no externally managed (PEP 668) system Python on this machine")
    out = _run_setup_dry(system)
    assert "PEP 668" in out and "/.venv" in out


def test_tools_test_runs_in_the_project_venv(tmp_path):
    """tools/test uses .venv/bin/python when setup made a .venv (and no other venv is active)."""
    fake = tmp_path / "repo"
    (fake / "tools").mkdir(parents=True)
    (fake / "tests").mkdir()
    shutil.copy(REPO / "tools" / "test", fake / "tools" / "test")
    (fake / "tests" / "test_where.py").write_text("import sys\n\ndef test_where():\n    print('PREFIX', sys.prefix)\n")
    venv.create(fake / ".venv", with_pip=False, system_site_packages=True)  # pytest from this Python's site
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHON")}
    env["FAVORMAP_TEST_WORKERS"] = "0"  # in one process: -s shows the test's print
    r = subprocess.run(
        ["bash", str(fake / "tools" / "test"), "-s", "-q", "-p", "no:cacheprovider"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"PREFIX {fake / '.venv'}" in r.stdout
    assert re.search(r"^1 passed", r.stdout, re.M), r.stdout


def test_tools_test_runs_the_tests_in_parallel_workers(tmp_path):
    """tools/test spreads the tests over pytest-xdist workers, FAVORMAP_TEST_WORKERS of them (default: one per
    CPU), each with OpenMP threads for its share of the CPUs; a -n on the command line wins."""
    pytest.importorskip("xdist")
    fake = tmp_path / "repo"
    (fake / "tools").mkdir(parents=True)
    (fake / "tests").mkdir()
    shutil.copy(REPO / "tools" / "test", fake / "tools" / "test")
    shutil.copy(REPO / "tests" / "conftest.py", fake / "tests" / "conftest.py")
    out = tmp_path / "seen"
    out.mkdir()
    (fake / "tests" / "test_where.py").write_text(
        "import os, pathlib, pytest\n\n"
        "@pytest.mark.parametrize('i', range(8))\n"
        "def test_where(i):\n"
        f"    pathlib.Path({str(out)!r}, str(i)).write_text("
        "os.environ.get('PYTEST_XDIST_WORKER', 'main') + ' ' + os.environ.get('OMP_NUM_THREADS', '-'))\n"
    )
    # not this run's own worker variables (PYTEST_XDIST_WORKER, ..._COUNT) nor the threads its conftest set
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "OMP_NUM_THREADS")}
    env = {k: v for k, v in env.items() if not k.startswith("PYTEST_")}
    env["PYTHON"] = sys.executable

    def run(workers, *args):
        for f in out.iterdir():
            f.unlink()
        r = subprocess.run(
            ["bash", str(fake / "tools" / "test"), "-q", "-p", "no:cacheprovider", *args],
            env=dict(env, FAVORMAP_TEST_WORKERS=workers),
            capture_output=True,
            text=True,
            timeout=120,
            cwd=tmp_path,
        )
        assert r.returncode == 0 and re.search(r"^8 passed", r.stdout, re.M), r.stdout + r.stderr
        seen = [f.read_text().split() for f in out.iterdir()]
        assert len(seen) == 8
        return {w for w, _ in seen}, {t for _, t in seen}

    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    workers, threads = run("2")
    assert workers <= {"gw0", "gw1"} and len(workers) >= 1
    assert threads == {str(max(1, cpus // 2))}
    assert run("0") == ({"main"}, {"-"})
    assert run("2", "-n", "0")[0] == {"main"}  # the command line's -n wins


def test_quiet_runs_still_print_the_summary_line(tmp_path):
    """With the project's pytest configuration, `-q` (as developers add it) keeps "N passed"."""
    (tmp_path / "test_one.py").write_text("def test_one():\n    pass\n")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-c",
            str(REPO / "pyproject.toml"),
            "--rootdir",
            str(tmp_path),
            "-q",
            "-p",
            "no:cacheprovider",
            str(tmp_path / "test_one.py"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(r"^1 passed", r.stdout, re.M), r.stdout


def test_wheel_install_finds_its_schema(tmp_path, small_map):
    """`pip wheel` + `pip install --target`: `favormap validate` finds the schema shipped as package data."""
    _, map_path = small_map
    wheels, target, src = tmp_path / "wheels", tmp_path / "target", tmp_path / "src"
    for name in ("favormap", "schemas"):  # a copy, so that the build leaves the checkout alone
        shutil.copytree(REPO / name, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    (whl,) = wheels.glob("favormap-*.whl")
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(whl)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    assert (target / "favormap" / "schemas" / "favormap-map.v1.json").is_file()
    assert not (target / "favormap" / "schemas").is_symlink()
    env = {**os.environ, "PYTHONPATH": str(target), "RERUN_ANALYTICS": "false"}
    code = "import sys, favormap; from favormap.cli import main; print(favormap.__file__); sys.exit(main(sys.argv[1:]))"
    r = subprocess.run(
        [sys.executable, "-c", code, "validate", str(map_path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env=env,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.splitlines()[0].startswith(str(target))
    assert "valid" in r.stdout.lower()


@pytest.mark.parametrize("script", sorted(p.name for p in (REPO / "tools").glob("bench_*.py")))
def test_benchmark_help_works(script):
    """Each benchmark's --help prints its usage (a '%' in a help text once broke bench_accuracy's)."""
    r = subprocess.run([sys.executable, str(REPO / "tools" / script), "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "usage:" in r.stdout, r.stderr[-500:]


def _bench_accuracy():
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_accuracy", REPO / "tools" / "bench_accuracy.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_accuracy"] = bench  # its dataclasses look their module up
    try:
        spec.loader.exec_module(bench)
    finally:
        del sys.modules["bench_accuracy"]
    return bench


def test_accuracy_benchmark_reuses_a_map_built_before_a_config_field_existed():
    """tools/bench_accuracy.py --reuse: a map stamped with a config that lacks a field added since
    (at its default) is the same map; any other difference (a field's value, the frames) is not."""
    import json

    from favormap.build import BuildConfig

    bench = _bench_accuracy()

    def key(cfg, frames=("a", "b")):
        return json.dumps(cfg.to_dict(), sort_keys=True, default=str) + str(list(frames))

    now = BuildConfig()
    old = now.to_dict()
    del old["voxel"]["patch_stride"], old["max_side"]  # as written before these fields existed
    stamp = json.dumps(old, sort_keys=True, default=str) + str(["a", "b"])
    assert bench.same_build(stamp, key(now)) and bench.same_build(key(now), key(now))
    other = BuildConfig()
    other.voxel.patch_stride = 3  # the new field, not at its default
    assert not bench.same_build(stamp, key(other))
    other = BuildConfig()
    other.voxel.seed = 1
    assert not bench.same_build(stamp, key(other))
    assert not bench.same_build(stamp, key(now, ("a", "c")))
    # a field whose default changed the maps: a stamp without it was built without it
    del old["min_frame_landmarks"]
    stamp = json.dumps(old, sort_keys=True, default=str) + str(["a", "b"])
    assert not bench.same_build(stamp, key(now))
    assert bench.same_build(stamp, key(BuildConfig(min_frame_landmarks=0)))


def test_accuracy_benchmark_does_not_reuse_a_map_whose_cameras_were_read_otherwise(small_sequence):
    """tools/bench_accuracy.py --reuse: the same frames read with another camera (a reader that changed a
    focal length) make another map."""
    import dataclasses

    from favormap.build import BuildConfig

    bench = _bench_accuracy()
    cfg = BuildConfig()
    key = bench.build_key(cfg, small_sequence)
    assert bench.same_build(key, bench.build_key(cfg, small_sequence))
    cams = {
        i: dataclasses.replace(c, params=[1.1 * float(v) for v in c.params]) for i, c in small_sequence.cameras.items()
    }
    refocused = dataclasses.replace(small_sequence, cameras=cams)
    assert not bench.same_build(key, bench.build_key(cfg, refocused))


def test_accuracy_benchmark_rows_round_trip_plain_and_gzipped(tmp_path):
    """tools/bench_accuracy.py --json NAME.json.gz writes gzip-compressed rows (docs/benchmarks keeps them
    so), NAME.json plain JSON; --compare reads both, and the committed runs it points to."""
    import gzip
    import json

    bench = _bench_accuracy()
    rows = [{"split": "orbit", "method": "rendered", "median_translation": 0.0005, "per_query": [{"t_err": 1e-4}]}]
    bench.write_rows(tmp_path / "a.json.gz", rows)
    bench.write_rows(tmp_path / "a.json", rows)
    assert json.loads(gzip.decompress((tmp_path / "a.json.gz").read_bytes())) == rows
    assert json.loads((tmp_path / "a.json").read_text()) == rows
    assert bench.read_rows(tmp_path / "a.json.gz") == bench.read_rows(tmp_path / "a.json") == rows
    assert (tmp_path / "a.json.gz").stat().st_size < (tmp_path / "a.json").stat().st_size
    runs = sorted((REPO / "docs" / "benchmarks").glob("accuracy-*.json.gz"))
    assert runs and not list((REPO / "docs" / "benchmarks").glob("*.json"))  # every committed run compressed
    assert all(isinstance(bench.read_rows(p), list) for p in runs[-2:])


def test_accuracy_benchmark_groups_rows_across_training_seeds():
    """tools/bench_accuracy.py --train-seeds: the rows of a map's seed copies (NAME-sK, or sK for the
    default map) are grouped with that map's rows, per split, prior and method."""
    from favormap.build import BuildConfig

    bench = _bench_accuracy()

    def cfg(seed):
        c = BuildConfig()
        c.voxel.seed = seed
        return c

    build_cfgs = [("", cfg(0)), ("s2", cfg(2)), ("b", cfg(0)), ("b-s2", cfg(2))]

    def row(variant, method, med, loc=3, fs=0):
        return dict(split="fox", prior="noise", map_variant=variant, method=method, median_translation=med,
                    localized=loc, queries=3, false_successes=fs)  # fmt: skip

    rows = [
        row("", "rendered", 0.002),
        row("s2", "s2 rendered", 0.004, loc=2, fs=1),
        row("b", "b rendered", 0.003),
        row("b-s2", "b-s2 rendered", None, loc=0),
        dict(split="fox", prior="none", method="pycolmap-SIFT", median_translation=0.001),  # no map: left out
    ]
    table = bench.seed_table(rows, build_cfgs).splitlines()
    assert table[2] == "| fox | noise | rendered | 0,2 | 0.0020 / 0.0040 | 0.0020-0.0040 | 0.0030 | 5/6 | 1 |"
    assert table[3] == "| fox | noise | b rendered | 0,2 | 0.0030 / - | 0.0030-0.0030 | 0.0030 | 3/6 | 0 |"
    assert len(table) == 4


def test_accuracy_benchmark_pairs_each_method_with_the_reference_query_by_query():
    """tools/bench_accuracy.py's paired table: a method's errors over the reference's, query by query
    on the same map and prior mode (geometric mean, bootstrap interval, lower/higher counts), the
    baseline against the first map's reference, per angle bin where queries have angles."""
    bench = _bench_accuracy()

    def q(name, err, angle=None, ok=True):
        return dict(name=name, t_err=err, success=ok, **({} if angle is None else {"angle_deg": angle}))

    ref = [q("a", 1e-3, 5), q("b", 2e-3, 15), q("c", 4e-3, 15), q("d", 1e-3, 50)]
    half = [q(x["name"], x["t_err"] / 2, x["angle_deg"]) for x in ref]  # twice as accurate on every query
    mixed = [q("a", 2e-3, 5), q("b", 1e-3, 15), q("c", 4e-3, 15), q("d", 1e-3, 50, ok=False)]
    rows = [
        dict(split="orbit", prior="noise", map_variant="", method="rendered", per_query=ref),
        dict(split="orbit", prior="noise", map_variant="", method="mean", per_query=half),
        dict(split="orbit", prior="noise", map_variant="w6", method="w6 mean", per_query=mixed),
        dict(split="orbit", prior="noise", map_variant="w6", method="w6 rendered", per_query=half),
        dict(split="orbit", prior="none", method="pycolmap-SIFT", per_query=mixed),  # the baseline
    ]
    pr = {(p["method"], p["reference"]): p for p in bench.paired_rows(rows)}
    assert set(pr) == {("mean", "rendered"), ("w6 mean", "w6 rendered"), ("pycolmap-SIFT", "rendered")}
    p = pr["mean", "rendered"]
    assert p["all"]["ratio"] == pytest.approx(0.5) and p["all"]["ci95"] == pytest.approx([0.5, 0.5])
    assert (p["all"]["lower"], p["all"]["higher"], p["failed"]) == (4, 0, (0, 0))
    assert p["bins"]["10-20"]["queries"] == 2 and p["bins"]["40-180"] is None  # one query: no ratio
    w = pr["w6 mean", "w6 rendered"]  # (2/0.5, 1/1, 4/2) on the three localized queries
    assert w["failed"] == (1, 0) and w["all"]["queries"] == 3
    assert w["all"]["ratio"] == pytest.approx((4 * 1 * 2) ** (1 / 3))
    assert (w["all"]["lower"], w["all"]["higher"]) == (0, 2)  # one tie
    lo, hi = w["all"]["ci95"]
    assert 1 <= lo <= w["all"]["ratio"] <= hi <= 4
    b = pr["pycolmap-SIFT", "rendered"]  # against the default map's rendered: (2, 0.5, 1)
    assert b["all"]["ratio"] == pytest.approx(1.0) and (b["all"]["lower"], b["all"]["higher"]) == (1, 1)
    table = bench.paired_table(rows).splitlines()
    assert table[-1].startswith("| orbit | none | pycolmap-SIFT | 1 / 0 | 1.00 [") and len(table) == 7


def test_accuracy_benchmark_pairs_map_variants_with_the_default_map_over_seeds():
    """tools/bench_accuracy.py --train-seeds / --build-variant: each method of each map variant is
    paired with the default map's reference of the same seed, query by query, the log ratios
    averaged over the seeds; the baseline with every seed's reference."""
    import numpy as np

    from favormap.build import BuildConfig

    bench = _bench_accuracy()

    def cfg(seed):
        c = BuildConfig()
        c.voxel.seed = seed
        return c

    build_cfgs = [("", cfg(0)), ("s1", cfg(1)), ("b", cfg(0)), ("b-s1", cfg(1))]

    def row(variant, method, errs, prior="noise"):
        pq = [dict(name=n, t_err=e, success=np.isfinite(e), angle_deg=a) for (n, a), e in zip(queries, errs)]
        return dict(split="orbit", prior=prior, map_variant=variant, method=method, per_query=pq)

    queries = [("a", 5.0), ("b", 15.0), ("c", 15.0)]
    ref0, ref1 = [1.0, 2.0, 4.0], [2.0, 2.0, 2.0]
    rows = [
        row("", "rendered", ref0),
        row("", "mean", [2.0, 4.0, 8.0]),  # seed 0: twice the reference on every query
        row("s1", "s1 rendered", ref1),
        row("s1", "s1 mean", [2.0, 2.0, 2.0]),  # seed 1: the same
        row("b", "b rendered", [0.5, 1.0, np.inf]),  # failed on c
        row("b-s1", "b-s1 rendered", [1.0, 1.0, 1.0]),
        dict(split="orbit", prior="none", method="pycolmap-SIFT", per_query=row("", "x", [2.0, 2.0, 2.0])["per_query"]),
    ]
    pr = {(p["map"], p["method"]): p for p in bench.seed_paired_rows(rows, build_cfgs)}
    assert set(pr) == {("", "mean"), ("b", "rendered"), ("(baseline)", "pycolmap-SIFT")}
    mean = pr["", "mean"]  # per query: mean of (log 2, log 1) = log sqrt(2)
    assert mean["seeds"] == [0, 1] and mean["all"]["ratio"] == pytest.approx(np.sqrt(2))
    assert mean["all"]["queries"] == 3 and mean["all"]["lower"] == 0 and mean["all"]["higher"] == 3
    b = pr["b", "rendered"]  # a: (1/2, 1/2), b: (1/2, 1/2); c failed on seed 0: left out
    assert b["all"]["queries"] == 2 and b["all"]["ratio"] == pytest.approx(0.5)
    assert b["bins"]["10-20"] is None and b["bins"]["0-10"] is None  # one query each: no interval
    base = pr["(baseline)", "pycolmap-SIFT"]  # against ref0 (2, 1, 0.5) and ref1 (1, 1, 1)
    assert base["seeds"] == [0, 1]
    expected = np.exp(np.mean([np.mean([np.log(2), 0]), 0, np.mean([np.log(0.5), 0])]))
    assert base["all"]["ratio"] == pytest.approx(expected)
    table = bench.seed_paired_table(rows, build_cfgs).splitlines()
    assert table[4].startswith("| orbit | noise | (default) | mean | 0,1 | 1.41 [") and len(table) == 7


def test_accuracy_benchmark_compares_two_runs_query_by_query_and_seed_by_seed():
    """tools/bench_accuracy.py --compare REF NEW: the same method of the same map variant and seed in
    two runs (two versions of the code), paired query by query, log ratios averaged over the seeds
    that both runs have; rows only one run has are left out."""
    import numpy as np

    bench = _bench_accuracy()
    queries = [("a", 5.0), ("b", 15.0), ("c", 25.0)]

    def row(variant, method, errs):
        pq = [dict(name=n, t_err=e, success=np.isfinite(e), angle_deg=a) for (n, a), e in zip(queries, errs)]
        return dict(split="orbit", prior="noise", map_variant=variant, method=method, per_query=pq)

    old = [
        row("", "rendered", [1.0, 2.0, 4.0]),
        row("s1", "s1 rendered", [2.0, 2.0, 2.0]),
        row("", "mean", [1.0, 1.0, 1.0]),
        row("lm6k-s2", "lm6k-s2 rendered", [1.0, 1.0, 1.0]),
    ]
    new = [
        row("", "rendered", [0.5, 1.0, 2.0]),  # seed 0: half on every query
        row("s1", "s1 rendered", [2.0, 2.0, np.inf]),  # seed 1: the same, failed on c
        row("s2", "s2 rendered", [9.0, 9.0, 9.0]),  # no seed 2 in the reference run: left out
        row("lm6k-s2", "lm6k-s2 rendered", [3.0, 3.0, 3.0]),
    ]
    got = {(p["map"], p["method"]): p for p in bench.compare_rows(old, new)}
    assert set(got) == {("", "rendered"), ("lm6k", "rendered")}
    r = got["", "rendered"]
    assert r["seeds"] == [0, 1]
    assert r["all"]["queries"] == 2 and r["all"]["ratio"] == pytest.approx(np.sqrt(0.5))  # c: inf, left out
    assert r["bins"]["0-10"] is None  # one query: no interval
    assert got["lm6k", "rendered"]["seeds"] == [2] and got["lm6k", "rendered"]["all"]["ratio"] == pytest.approx(3.0)
    table = bench.compare_table(old, new).splitlines()
    assert table[4].startswith("| orbit | noise | (default) | rendered | 0,1 | 0.71 [") and len(table) == 6


def test_accuracy_benchmark_pools_runs_query_by_query():
    """tools/bench_accuracy.py --pool RUN RUN ...: each query localized where most runs localized it, with the
    median of those runs' errors; a row missing from one run is left out."""
    import numpy as np

    bench = _bench_accuracy()

    def row(method, errs, prior="none"):
        pq = [
            dict(name=n, t_err=e, r_err_deg=e / 10, success=bool(np.isfinite(e)), nees=None)
            for n, e in zip("abc", errs)
        ]
        return dict(split="fox-holdout", prior=prior, map_variant="", method=method, per_query=pq)

    inf = np.inf
    runs = [
        [row("pycolmap-SIFT", [1.0, 2.0, inf]), row("rendered", [1.0, 1.0, 1.0], "noise")],
        [row("pycolmap-SIFT", [3.0, inf, inf])],
        [row("pycolmap-SIFT", [2.0, 6.0, 5.0])],
    ]
    pooled = bench.pool_rows(runs)
    assert [r["method"] for r in pooled] == ["pycolmap-SIFT"]  # "rendered" is in one run only
    q = {x["name"]: x for x in pooled[0]["per_query"]}
    assert q["a"]["success"] and q["a"]["t_err"] == 2.0 and q["a"]["r_err_deg"] == pytest.approx(0.2)
    assert q["b"]["success"] and q["b"]["t_err"] == 4.0  # two of three localized it: the median of those two
    assert not q["c"]["success"]  # one of three


def test_accuracy_benchmark_measures_the_error_both_methods_share():
    """The real table's shared error: over the queries both methods localize, the median distance between
    their estimated camera centres and the median cosine between their error vectors."""
    import numpy as np

    bench = _bench_accuracy()

    def row(vecs):
        pq = [
            dict(name=n, success=v is not None, t_err=np.linalg.norm(v) if v else np.inf, t_vec=v)
            for n, v in zip("abcd", vecs)
        ]
        return dict(per_query=pq)

    fav = row([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 1.0], [5.0, 0, 0]])
    base = row([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0], None])  # d failed: left out
    got = bench.shared_error(fav, base, list("abcd"))
    assert got["queries"] == 3
    assert got["apart"] == pytest.approx(1.0)  # 0, 1, 2
    assert got["cosine"] == pytest.approx(1.0)  # 1, 1, -1
    assert bench.shared_error(fav, row([None, None, [0, 0, 1.0], None]), list("abcd")) is None


def test_accuracy_benchmark_reads_a_pseudo_ground_truth_by_frame_stem(tmp_path):
    """--splits 7scenes-*-pgt: the frames keep their images and take the poses and focal of the pseudo
    ground truth file, matched by file stem; a frame the file lacks is refused."""
    import numpy as np

    from favormap.geometry import camera_centers
    from favormap.io.types import Camera, Frame, Sequence

    bench = _bench_accuracy()
    cam = Camera("PINHOLE", 640, 480, [585.0, 585.0, 320.0, 240.0])
    frames = [Frame(f"frame-{i:06d}.color.jpg", tmp_path / f"frame-{i:06d}.color.jpg", 0, np.eye(4)) for i in (5, 10)]
    seq = Sequence(tmp_path, "7scenes-flat", {0: cam}, frames)
    pgt = tmp_path / "pgt.txt"
    pgt.write_text(
        "# comment\n"
        "seq-01/frame-000005.color.png 1 0 0 0 0.5 0 0 525.5\n"
        "seq-01/frame-000010.color.png 0 0 0 1 0 0 2 525.5\n"  # 180 degrees about z
    )
    got = bench.with_pseudo_ground_truth(seq, pgt)
    assert [f.image_path for f in got.frames] == [f.image_path for f in frames]
    assert got.cameras[0].params.tolist() == [525.5, 525.5, 320.0, 240.0]
    centres = camera_centers(np.stack([f.cam_from_world for f in got.frames]))
    assert centres == pytest.approx(np.array([[-0.5, 0, 0], [0, 0, -2.0]]))
    assert got.frames[1].cam_from_world[:3, :3] == pytest.approx(np.diag([-1.0, -1.0, 1.0]))
    pgt.write_text("seq-01/frame-000005.color.png 1 0 0 0 0 0 0 525.5\n")
    with pytest.raises(SystemExit, match="no pose for frame frame-000010"):
        bench.with_pseudo_ground_truth(seq, pgt)


def test_the_shipped_7scenes_pseudo_ground_truth_covers_the_benchmark_frames():
    """tools/data's SfM pseudo ground truth: frames 500-995 of the 7-Scenes set, every 5th, rotations
    as unit quaternions, one focal."""
    import numpy as np

    bench = _bench_accuracy()
    rows = [line.split() for line in bench.SEVENSCENES_PGT.read_text().splitlines() if not line.startswith("#")]
    assert [r[0] for r in rows] == [f"seq-01/frame-{i:06d}.color.png" for i in range(500, 1000, 5)]
    q = np.array([[float(v) for v in r[1:5]] for r in rows])
    assert np.linalg.norm(q, axis=1) == pytest.approx(np.ones(100), abs=1e-5)
    assert {r[8] for r in rows} == {"525.505"}


def test_accuracy_benchmark_gives_the_suite_geometric_mean_an_interval():
    """The suite's one figure, the geometric mean of the splits' paired ratios, with a 95 % bootstrap
    interval that resamples each split's queries; stored runs without per-query ratios get none."""
    import numpy as np

    bench = _bench_accuracy()
    flat = [
        {"map": "(default)", "ratio": {"ratio": 2.0, "log_ratios": [np.log(2.0)] * 3}},
        {"map": "(default)", "ratio": {"ratio": 0.5, "log_ratios": [np.log(0.5)] * 4}},
    ]
    value, ci = bench.geometric_means(flat)["(default)"]
    assert value == pytest.approx(1.0) and ci == pytest.approx([1.0, 1.0])
    spread = [{"map": "v", "ratio": bench.paired_ratio(np.array([1.0, 2.0, 4.0, 1.0]), np.ones(4))}]
    spread.append({"map": "v", "ratio": bench.paired_ratio(np.array([0.5, 1.0, 1.0]), np.ones(3))})
    value, (lo, hi) = bench.geometric_means(spread)["v"]
    expected = np.exp(np.mean([np.mean(np.log([1, 2, 4, 1])), np.mean(np.log([0.5, 1, 1]))]))
    assert value == pytest.approx(expected) and lo < value < hi
    assert bench.geometric_means([{"map": "old", "ratio": {"ratio": 0.8}}]) == {"old": (pytest.approx(0.8), None)}


def test_accuracy_benchmark_takes_favormaps_median_over_noise_priors():
    """--prior-seeds: each query's favormap result is the one whose error is the median over its priors
    (a failure counts as infinite), as the baseline's is over RANSAC seeds; a result already computed
    for the first prior is not computed again."""
    from types import SimpleNamespace

    import numpy as np

    bench = _bench_accuracy()

    def pose(x):
        T = np.eye(4)
        T[0, 3] = -x  # camera centre at (x, 0, 0)
        return T

    calls = []

    class Loc:
        def localize(self, image, prior, cam):
            calls.append(prior)
            return SimpleNamespace(success=prior != "fail", cam_from_world=pose({"b": 3.0, "c": 2.0}.get(prior, 0.0)))

    fr = SimpleNamespace(image_path="q.png", cam_from_world=pose(0.0))
    first = SimpleNamespace(success=True, cam_from_world=pose(1.0))
    prior, res = bench.median_over_priors(Loc(), fr, None, [("a", first), ("b", None), ("c", None)])
    assert prior == "c" and calls == ["b", "c"]  # errors 1, 3, 2: the median is c's
    prior, res = bench.median_over_priors(Loc(), fr, None, [("a", first), ("fail", None), ("b", None)])
    assert prior == "b" and res.success  # 1, inf, 3: the median is 3
