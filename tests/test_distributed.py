"""Distributed build on a local two-worker Ray instance (favormap.distributed).

Skipped when Ray is not installed (``pip install 'favormap[distributed]'``; tools/setup.sh installs it)."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from conftest import small_build_config

os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
ray = pytest.importorskip(
    "ray", reason="Ray is not installed (pip install 'favormap[distributed]'): distributed build tests skipped"
)

CFG = dict(iterations=30, max_landmarks=150, train_batch=50)  # 3 training batches


@pytest.fixture(scope="module")
def ray_two_workers():
    """A local Ray instance with two CPU slots (two worker processes run tasks at a time), started
    the way ``favormap build --ray local`` starts one (``ray.init(num_cpus=2)``, no dashboard, no usage
    statistics, the driver's favormap code shipped to the workers)."""
    from favormap.distributed import RayExecutor

    if ray.is_initialized():
        ray.shutdown()
    with RayExecutor("local", num_cpus=2) as ex:
        assert ex.context is not None and not ex.context.dashboard_url  # no dashboard
        assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"
        yield ex
    assert not ray.is_initialized()


@pytest.fixture(scope="module")
def local_map(small_sequence):
    from favormap.build import build_map

    return build_map(small_sequence, small_build_config(**CFG))


def _assert_same_map(a, b):
    """Same landmarks (positions, tracks) and descriptors per landmark with cosine >= 0.999 at every node."""
    assert len(a.positions) == len(b.positions) > 0
    np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a.track_landmark, b.track_landmark)
    np.testing.assert_array_equal(a.track_frame, b.track_frame)
    L, C = len(a.positions), a.channels
    da, db = a.descriptors.reshape(L, -1, C), b.descriptors.reshape(L, -1, C)
    cos = (da * db).sum(-1) / np.maximum(np.linalg.norm(da, axis=-1) * np.linalg.norm(db, axis=-1), 1e-12)
    assert cos.min(axis=1).min() >= 0.999, f"worst landmark cosine {cos.min():.6f}"
    np.testing.assert_allclose(a.density, b.density, atol=1e-3)
    np.testing.assert_allclose(a.mean_descriptor, b.mean_descriptor, atol=1e-5)


class _Killer:
    """Kills (SIGKILL) the first worker process found running a Ray task named ``favormap.<fn>``
    (Ray sets a worker's process title to ``ray::<task name>`` while it runs the task)."""

    def __init__(self, fn_name: str):
        self.title = f"ray::favormap.{fn_name}".encode()
        self.killed: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self):
        while not self._stop.is_set() and not self.killed:
            for p in os.listdir("/proc"):
                if not p.isdigit():
                    continue
                try:
                    with open(f"/proc/{p}/cmdline", "rb") as f:
                        title = f.read()
                except OSError:
                    continue
                if title.startswith(self.title) and self._busy(p):
                    os.kill(int(p), signal.SIGKILL)
                    self.killed.append(int(p))
                    return
            time.sleep(0.01)

    def _busy(self, pid: str) -> bool:
        """Still running the task: it used CPU within the last 50 ms and still has the task's title
        (a worker that has just finished may keep the title for a moment)."""

        def cpu():
            with open(f"/proc/{pid}/stat") as f:
                v = f.read().rsplit(")", 1)[1].split()
            return int(v[11]) + int(v[12])

        try:
            a = cpu()
            time.sleep(0.05)
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                return cpu() > a and f.read().startswith(self.title)
        except (OSError, IndexError, ValueError):
            return False

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(5)


def test_ray_build_same_map_as_single_process(ray_two_workers, small_sequence, local_map):
    from favormap.build import build_map
    from favormap.distributed import RayExecutor

    with RayExecutor("auto") as ex:
        assert ex.cluster_cpus == 2
        m = build_map(small_sequence, small_build_config(**CFG), executor=ex)
    assert ray.is_initialized()  # an executor that found Ray running leaves it running
    _assert_same_map(local_map, m)
    prov = m.provenance["executor"]
    assert prov["name"] == "ray" and prov["cpus"] == 2 and prov["nodes"] == 1
    assert local_map.provenance["executor"]["name"] == "local"


def test_ray_build_survives_a_killed_worker(ray_two_workers, small_sequence, local_map):
    from favormap.build import build_map
    from favormap.distributed import RayExecutor

    with RayExecutor("auto", max_retries=2) as ex, _Killer("train_batch") as killer:
        m = build_map(small_sequence, small_build_config(**CFG), executor=ex)
    assert len(killer.killed) == 1  # a worker died mid-training; Ray re-ran its batch
    _assert_same_map(local_map, m)


def test_ray_build_with_a_dead_worker_and_no_retries_writes_no_map(ray_two_workers, small_sequence, tmp_path, capsys):
    from favormap.cli import main

    out = tmp_path / "map.h5"
    args = [
        "build",
        str(small_sequence.root),
        "-o",
        str(out),
        "--resize",
        "0",
        "--max-keypoints",
        "1024",
        "--max-landmarks",
        "150",
        "--quality",
        "fast",
        "--iterations",
        "150",
        "--train-batch",
        "50",
        "--ray",
        "auto",
        "--ray-retries",
        "0",
        "-q",
    ]
    with _Killer("train_batch") as killer:
        rc = main(args)
    assert len(killer.killed) == 1
    err = capsys.readouterr().err.strip()
    assert rc == 1, err
    assert err.count("\n") == 0 and "favormap build: error: a Ray worker running train_batch died" in err, err
    assert list(tmp_path.iterdir()) == []  # no map, no temporary left behind
    assert ray.is_initialized()


def test_ray_task_error_is_one_clear_error(ray_two_workers, small_sequence, tmp_path):
    """An error inside a task (here: an unreadable image) reaches the driver as the build's own error."""
    import shutil

    from favormap.build import build_map
    from favormap.distributed import RayExecutor
    from favormap.errors import InputError
    from favormap.io import read_sequence

    root = tmp_path / "seq"
    shutil.copytree(small_sequence.root, root)
    seq = read_sequence(root)
    seq.frames[3].image_path.write_bytes(b"not an image")
    with RayExecutor("auto") as ex, pytest.raises(InputError, match="not a readable image"):
        build_map(seq, small_build_config(**CFG), executor=ex)


def test_ray_worker_with_other_code_is_refused(ray_two_workers, small_sequence):
    """Workers must run the driver's favormap: a task seeing other code fails with one clear error."""
    from favormap.build import build_map
    from favormap.distributed import RayExecutor
    from favormap.errors import FavormapError

    with RayExecutor("auto") as ex, pytest.raises(FavormapError, match="runs other favormap code"):
        ex._fingerprint = "0" * 40  # as if the driver ran another version
        build_map(small_sequence, small_build_config(**CFG), executor=ex)
