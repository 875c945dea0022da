"""Several favormap users on one machine: thread-pool sizing, a Localizer shared by threads,
readers of a map while other processes write maps beside it."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from favormap import threads as thr
from favormap.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT), RERUN_ANALYTICS="false")


@pytest.fixture
def restore_pools():
    """Leave torch's and OpenCV's pools (and favormap's record of them) as they were."""
    import cv2
    import torch

    t, c, applied = torch.get_num_threads(), cv2.getNumThreads(), thr._applied
    yield
    torch.set_num_threads(t)
    cv2.setNumThreads(c)
    thr._applied = applied


# -- the rule ----------------------------------------------------------------------------------------
def test_explicit_count_beats_environment_beats_free_cpus(monkeypatch):
    monkeypatch.setattr(thr, "available_cpus", lambda: 7)
    monkeypatch.setattr(thr, "MIN_WINDOW_S", 0.0)
    busy = [0.0]
    monkeypatch.setattr(thr, "others_busy", lambda a, b: busy[0])
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert thr.resolve_threads() == 7
    for others, n in ((0.4, 7), (2.4, 5), (2.6, 4), (6.7, 1), (30.0, 1)):  # CPUs other processes keep busy
        busy[0] = others
        assert thr.resolve_threads() == n, others
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert thr.resolve_threads() == 3
    assert thr.resolve_threads(5) == 5
    monkeypatch.setenv("OMP_NUM_THREADS", "2,1")  # OpenMP nesting list: the outer level
    assert thr.resolve_threads() == 2
    busy[0] = 0.0
    for bad in ("0", "-1", "many", ""):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        assert thr.resolve_threads() == 7
    for bad in (0, -2, 1.5, "2", True):
        with pytest.raises(InputError, match="positive integer"):
            thr.resolve_threads(bad)


def test_others_busy_leaves_out_this_process():
    a, b = thr._Sample(), thr._Sample()
    a.t, a.own, a.busy = 10.0, 1.0, 100.0
    b.t, b.own, b.busy = 12.0, 2.5, 103.5  # 3.5 busy CPU-seconds in 2 s, 1.5 of them ours
    assert thr.others_busy(a, b) == pytest.approx(1.0)
    b.busy = None  # no /proc/stat
    assert thr.others_busy(a, b) is None
    # the real counters move forward
    s0 = thr._Sample()
    sum(i * i for i in range(200_000))
    s1 = thr._Sample()
    assert s1.t > s0.t and s1.own >= s0.own
    assert s0.busy is None or s1.busy >= s0.busy


def test_a_busy_machine_takes_threads_away_and_gives_them_back(monkeypatch, restore_pools):
    import torch

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(thr, "available_cpus", lambda: 2)
    monkeypatch.setattr(thr, "MIN_WINDOW_S", 0.0)
    busy = [0.0]
    monkeypatch.setattr(thr, "others_busy", lambda a, b: busy[0])
    thr._applied = None
    assert thr.configure_threads() == 2 and torch.get_num_threads() == 2
    busy[0] = 1.2  # a second process started
    assert thr.rebalance() == 2  # not yet: at most every REBALANCE_S
    monkeypatch.setattr(thr, "REBALANCE_S", 0.0)
    assert thr.rebalance() == 1 and torch.get_num_threads() == 1
    busy[0] = 0.1  # it ended
    assert thr.rebalance() == 2 and torch.get_num_threads() == 2
    thr.configure_threads(1)  # an explicit count is never rebalanced
    busy[0] = 0.0
    assert thr.rebalance() == 1 and torch.get_num_threads() == 1


def _fake_cgroup(tmp_path, proc_lines: str, files: dict) -> tuple[Path, Path]:
    root = tmp_path / "cg"
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    proc = tmp_path / "proc_cgroup"
    proc.write_text(proc_lines)
    return root, proc


def test_cgroup_v2_quota_is_read_up_the_hierarchy(tmp_path):
    root, proc = _fake_cgroup(
        tmp_path,
        "0::/jobs/a\n",
        {"jobs/a/cpu.max": "max 100000\n", "jobs/cpu.max": "150000 100000\n", "cpu.max": "max 100000\n"},
    )
    assert thr._cgroup_quota(root, proc) == pytest.approx(1.5)
    root, proc = _fake_cgroup(tmp_path / "b", "0::/\n", {"cpu.max": "max 100000\n"})
    assert thr._cgroup_quota(root, proc) is None


def test_cgroup_v1_quota(tmp_path):
    root, proc = _fake_cgroup(
        tmp_path,
        "4:cpu,cpuacct:/docker/x\n3:memory:/docker/x\n",
        {"cpu,cpuacct/docker/x/cpu.cfs_quota_us": "300000\n", "cpu,cpuacct/docker/x/cpu.cfs_period_us": "100000\n"},
    )
    assert thr._cgroup_quota(root, proc) == pytest.approx(3.0)
    root, proc = _fake_cgroup(
        tmp_path / "u", "4:cpu,cpuacct:/\n", {"cpu/cpu.cfs_quota_us": "-1\n", "cpu/cpu.cfs_period_us": "100000\n"}
    )
    assert thr._cgroup_quota(root, proc) is None


def test_available_cpus_is_affinity_capped_by_quota(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(thr, "_cgroup_quota", lambda: None)
    assert thr.available_cpus() == 4
    monkeypatch.setattr(thr, "_cgroup_quota", lambda: 2.5)
    assert thr.available_cpus() == 2
    monkeypatch.setattr(thr, "_cgroup_quota", lambda: 0.5)  # half a CPU still runs one thread
    assert thr.available_cpus() == 1


def test_configure_sizes_torch_and_opencv(restore_pools):
    import cv2
    import torch

    assert thr.configure_threads(1) == 1
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
    assert thr.configure_threads(None) == 1  # None keeps what was configured
    assert thr.configure_threads(2) == 2
    assert torch.get_num_threads() == 2 and cv2.getNumThreads() == 2


def test_serial_pools_hold_opencv_and_torch_at_one_thread_and_give_the_count_back(restore_pools):
    """LocalExecutor's thread pool: OpenCV and torch run each call in its calling thread while the
    block runs, a resize by the rule meanwhile (configure_threads, rebalance) takes effect on leaving,
    and nested blocks (two executors) restore only when the last one ends."""
    import cv2
    import torch

    thr.configure_threads(2)
    with thr.serial_pools():
        assert cv2.getNumThreads() == 1 and torch.get_num_threads() == 1
        thr.configure_threads(3)  # both follow on leaving
        assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
        with thr.serial_pools():
            assert cv2.getNumThreads() == 1 and torch.get_num_threads() == 1
        assert cv2.getNumThreads() == 1 and torch.get_num_threads() == 1
    assert cv2.getNumThreads() == 3 and torch.get_num_threads() == 3


def test_serial_blas_holds_blas_at_one_thread_while_any_block_is_open(restore_pools):
    """serial_blas (a localizer with the pools in its hands): BLAS runs each product in its calling thread
    while a block is open, OpenCV's pool keeps its size (the extraction uses it), blocks overlap (threads
    sharing one localizer, a serial_pools block inside) and BLAS gets its threads back when the last ends."""
    import cv2
    import numpy as np  # noqa: F401  (NumPy's BLAS is loaded)
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    thr.configure_threads(2)
    with threadpool_limits(2, user_api="blas"):
        assert blas() and set(blas()) == {2}
        with thr.serial_blas():
            assert set(blas()) == {1} and cv2.getNumThreads() == 2
            with thr.serial_pools():
                assert set(blas()) == {1} and cv2.getNumThreads() == 1
            assert set(blas()) == {1} and cv2.getNumThreads() == 2  # still held: the outer block is open
            with thr.serial_blas():
                assert set(blas()) == {1}
            assert set(blas()) == {1}
        assert set(blas()) == {2}


def test_a_fresh_process_follows_the_rule():
    show = "print(n, torch.get_num_threads(), cv2.getNumThreads(), torch.get_num_interop_threads())"
    env = {k: v for k, v in ENV.items() if k != "OMP_NUM_THREADS"}
    # configure_threads does not import torch (a SIFT localization never needs it); a command that
    # imports torch afterwards calls it again (the CLI's build_map and Localizer ask for it) and torch's
    # pools then follow the count already chosen
    code = (
        "import sys; from favormap.threads import configure_threads; n = configure_threads(); "
        "assert 'torch' not in sys.modules; import torch, cv2; assert configure_threads() == n; " + show
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    n, t, c, inter = map(int, out.stdout.split())
    assert 1 <= n <= thr.available_cpus() and t == c == n and inter == 1  # how many depends on the machine's load
    out = subprocess.run(
        [sys.executable, "-c", code], env=dict(env, OMP_NUM_THREADS="1"), capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["1", "1", "1", "1"]


def test_the_library_leaves_the_process_pools_and_heap_alone_unless_asked(small_map, small_sequence, tmp_path):
    """A program that embeds favormap keeps its own torch/OpenCV pool sizes and malloc policy: a build and a
    Localizer change neither unless given ``threads`` ("auto" or a count), in a fresh process; a Localizer given
    them sets both."""
    _, path = small_map
    frame = small_sequence.frames[3]
    code = f"""
import cv2, torch, numpy as np
torch.set_num_threads(3); cv2.setNumThreads(3)
from favormap import heap
from favormap.build import BuildConfig, build_map
from favormap.io import read_sequence
from favormap.localize import LocalizeConfig, Localizer
from favormap.voxels import VoxelConfig
seq = read_sequence({str(small_sequence.root)!r})
build_map(seq, BuildConfig(max_keypoints=400, max_side=0, max_landmarks=100, voxel=VoxelConfig.preset("quick")))
loc = Localizer({str(path)!r})
res = loc.localize({str(frame.image_path)!r}, np.asarray({frame.cam_from_world.tolist()!r}))
assert res.success, res.message
print(torch.get_num_threads(), cv2.getNumThreads(), heap._reusing)
Localizer({str(path)!r}, LocalizeConfig(threads=1))
print(torch.get_num_threads(), cv2.getNumThreads(), heap._reusing)
"""
    out = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.split("\n")
    assert lines[0].split() == ["3", "3", "False"], out.stdout
    assert lines[1].split() == ["1", "1", "True"], out.stdout


def test_cli_threads_option(small_map, restore_pools, capsys):
    import torch

    from favormap.cli import main

    _, path = small_map
    assert main(["query", str(path), "--near", "0", "0", "0", "--knn", "2", "--threads", "1", "--json"]) == 0
    assert torch.get_num_threads() == 1
    capsys.readouterr()
    for cmd in (
        ["build", "seq", "-o", "x.h5"],
        ["localize", "m.h5", "q.png"],
        ["eval", "m.h5", "seq"],
        ["merge", "a.h5", "b.h5", "-o", "c.h5"],
        ["prune", "a.h5", "-o", "b.h5"],
        ["demo"],
    ):
        with pytest.raises(SystemExit) as e:
            main(cmd + ["--threads", "0"])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--threads" in err and "positive integer" in err, err


# -- a Localizer shared by threads -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def queries(small_sequence):
    from favormap.geometry import perturb_pose
    from favormap.synthetic import make_room, random_views_near, render

    scene = make_room(0)
    poses = [f.cam_from_world for f in small_sequence.frames]
    views = random_views_near(poses, 4, seed=11, max_trans=0.1, max_rot_deg=5.0, scene=scene)
    cam = small_sequence.cameras[0]
    rng = np.random.default_rng(3)
    return [(render(scene, cam, T)[0], perturb_pose(T, 0.2, 10.0, rng)) for T in views]


def _key(res):
    return (
        bool(res.success),
        res.num_inliers,
        [it.num_matches for it in res.iterations],
        res.cam_from_world.round(9).tobytes(),
    )


def test_a_localizer_shared_by_threads_gives_the_single_threaded_results(small_map, queries):
    from favormap.localize import LocalizeConfig, Localizer

    _, path = small_map
    # a small voxel cache, so that the threads evict each other's grids while they read
    from favormap.mapfile import Map

    loc = Localizer(Map(path, cache_size=64), LocalizeConfig(iterations=2))
    expected = [_key(loc.localize(img, prior)) for img, prior in queries]
    assert sum(k[0] for k in expected) >= 3
    n_threads, rounds = 4, 2
    got: dict = {}
    errors = []
    start = threading.Barrier(n_threads)

    def work(t):
        try:
            start.wait()
            order = np.random.default_rng(t).permutation(len(queries) * rounds) % len(queries)
            got[t] = [(int(i), _key(loc.localize(*queries[i]))) for i in order]
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))

    ts = [threading.Thread(target=work, args=(t,)) for t in range(n_threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errors, errors
    for t in range(n_threads):
        assert len(got[t]) == len(queries) * rounds
        for i, key in got[t]:
            assert key == expected[i], (t, i)
    loc.close()


# -- readers while other processes write maps in the same folder -------------------------------------------
READER = r"""
import json, sys, time
from pathlib import Path
import numpy as np
from favormap.localize import Localizer, LocalizeConfig
path, spec, stop = sys.argv[1], json.loads(Path(sys.argv[2]).read_text()), Path(sys.argv[3])
loc = Localizer(path, LocalizeConfig(iterations=2, threads=1))
rounds = mismatches = 0
while rounds < 2 or not stop.exists():
    for q in spec["queries"]:
        res = loc.localize(np.load(q["image"]), np.array(q["prior"]))
        got = [bool(res.success), int(res.num_inliers), res.cam_from_world.round(9).tolist()]
        mismatches += got != q["expected"]
    rounds += 1
    if rounds == 1:
        print("ready", flush=True)
print(json.dumps({"rounds": rounds, "mismatches": mismatches}))
"""


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_readers_never_fail_while_other_processes_write_maps_beside_theirs(small_map, queries, tmp_path):
    """Two processes localize against a map while other processes prune and merge it into new maps
    in the same folder: every reader result equals the undisturbed one, the map is unchanged, and
    the written maps are complete."""
    import shutil

    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile.validate import validate

    _, src = small_map
    folder = tmp_path / "maps"
    folder.mkdir()
    path = folder / "shared.h5"
    shutil.copyfile(src, path)
    before = _sha(path)
    loc = Localizer(path, LocalizeConfig(iterations=2))
    spec = []
    for i, (img, prior) in enumerate(queries):
        np.save(tmp_path / f"q{i}.npy", img)
        r = loc.localize(img, prior)
        spec.append(
            {
                "image": str(tmp_path / f"q{i}.npy"),
                "prior": prior.tolist(),
                "expected": [bool(r.success), int(r.num_inliers), r.cam_from_world.round(9).tolist()],
            }
        )
    loc.close()
    (tmp_path / "spec.json").write_text(json.dumps({"queries": spec}))
    stop = tmp_path / "stop"
    readers = [
        subprocess.Popen(
            [sys.executable, "-c", READER, str(path), str(tmp_path / "spec.json"), str(stop)],
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    try:
        for p in readers:  # the readers are localizing before the first write starts
            assert p.stdout.readline().strip() == "ready", p.stderr.read()[-2000:]
        favormap = [sys.executable, "-m", "favormap"]
        writes = [
            ["prune", str(path), "-o", str(folder / "pruned.h5"), "--max-landmarks", "150"],
            ["merge", str(path), str(folder / "pruned.h5"), "-o", str(folder / "merged.h5")],
            ["prune", str(folder / "merged.h5"), "-o", str(folder / "pruned.h5"), "--min-track", "6"],
        ]
        for cmd in writes:  # one after the other, while the readers run
            r = subprocess.run(
                favormap + cmd + ["-q", "--threads", "1"], env=ENV, capture_output=True, text=True, timeout=300
            )
            assert r.returncode == 0, r.stderr
    finally:
        stop.touch()
    for p in readers:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
        res = json.loads(out.strip().splitlines()[-1])
        assert res["rounds"] >= 2 and res["mismatches"] == 0, res
    assert _sha(path) == before
    for name in ("pruned.h5", "merged.h5"):
        rep = validate(folder / name)
        assert rep.valid, rep.problems
    assert sorted(p.name for p in folder.iterdir()) == ["merged.h5", "pruned.h5", "shared.h5"]  # no partial files left
