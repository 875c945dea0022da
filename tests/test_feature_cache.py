"""The on-disk feature cache (favormap.features.cache): a build that streams its features from disk
is the same map as one in memory, reuses what the cache holds, and refuses damaged or foreign files."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from conftest import small_build_config

from favormap.errors import InputError

MAP_ARRAYS = ("positions", "descriptors", "density", "mean_descriptor", "track_frame", "track_xy", "voxel_size")


def _build(seq, cache, **over):
    from favormap.build import build_map

    return build_map(seq, small_build_config(iterations=20, max_landmarks=150, **over), feature_cache=cache)


@pytest.fixture(scope="module")
def memory_map(small_sequence):
    return _build(small_sequence, False)


def _same_map(a, b):
    for k in MAP_ARRAYS:
        assert np.array_equal(getattr(a, k), getattr(b, k)), k


def test_cached_build_is_the_in_memory_map_and_reuses_the_cache(small_sequence, memory_map, tmp_path):
    path = tmp_path / "features.h5"
    first = _build(small_sequence, path)
    _same_map(memory_map, first)
    assert first.provenance["stats"]["frames_extracted"] == len(small_sequence.frames)
    assert first.provenance["feature_cache"] == str(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "favormap-features" and len(f["frames"]) == len(small_sequence.frames)
    again = _build(small_sequence, path)  # nothing to extract
    _same_map(memory_map, again)
    assert again.provenance["stats"]["frames_extracted"] == 0
    # a changed image file (its size and time) is extracted again; the others are not
    img = small_sequence.frames[3].image_path
    st = os.stat(img)
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        third = _build(small_sequence, path)
    finally:
        os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert third.provenance["stats"]["frames_extracted"] == 1
    _same_map(memory_map, third)


def test_an_interrupted_cache_is_completed(small_sequence, memory_map, tmp_path):
    path = tmp_path / "features.h5"
    _build(small_sequence, path)
    with h5py.File(path, "a") as f:  # as if the build stopped while writing two frames
        names = sorted(f["frames"])
        f["frames"][names[0]].attrs["complete"] = False
        del f["frames"][names[5]]
    m = _build(small_sequence, path)
    assert m.provenance["stats"]["frames_extracted"] == 2
    _same_map(memory_map, m)


def test_long_sequences_stream_through_a_temporary_cache(small_sequence, memory_map, monkeypatch):
    from favormap import build

    monkeypatch.setattr(build, "MEMORY_FRAMES", 5)
    m = _build(small_sequence, None)
    where = m.provenance["feature_cache"]
    assert where != "memory" and not os.path.exists(where)  # used, then removed
    _same_map(memory_map, m)
    monkeypatch.setattr(build, "MEMORY_FRAMES", 100)
    assert _build(small_sequence, None).provenance["feature_cache"] == "memory"


def test_cache_refuses_other_settings_foreign_and_damaged_files(small_sequence, tmp_path):
    from favormap.features.cache import FeatureCache

    path = tmp_path / "features.h5"
    _build(small_sequence, path)
    with pytest.raises(InputError, match="other settings: max_keypoints 1024 \\(not 512\\)"):
        FeatureCache(path, "sift", 512, 0)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(InputError, match="is not a favormap feature cache"):
        FeatureCache(foreign, "sift", 1024, 0)
    with pytest.raises(InputError, match="is not a favormap feature cache"):
        FeatureCache(small_sequence.frames[0].image_path, "sift", 1024, 0)
    # flip bytes inside a descriptor dataset: the checksum turns it into an error, not wrong features
    damaged = tmp_path / "damaged.h5"
    shutil.copy(path, damaged)
    with h5py.File(damaged, "r") as f:
        ds = f["frames"][sorted(f["frames"])[2]]["descriptors"]
        offset = ds.id.get_chunk_info(0).byte_offset  # (checksummed datasets are chunked)
    with open(damaged, "r+b") as fh:
        fh.seek(offset + 64)
        fh.write(b"\xff" * 256)
    out = tmp_path / "map.h5"
    r = subprocess.run(
        [sys.executable, "-m", "favormap", "build", str(small_sequence.root), "-o", str(out), "--quality", "quick"]
        + ["--resize", "0", "--max-keypoints", "1024", "--feature-cache", str(damaged), "-q"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 1 and "is damaged" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize("name", ["sift", "xfeat"])
def test_sampling_state_round_trip(small_sequence, name):
    """An extractor's sampling state stored as arrays and read back samples the same descriptors."""
    from favormap.features import create
    from favormap.io.images import load_image

    ex = create(name, max_keypoints=256)
    fr = small_sequence.frames[0]
    img, _ = load_image(fr.image_path, small_sequence.cameras[fr.camera_id], 0)
    f = ex.extract(img)
    back = type(f)(
        f.keypoints,
        f.scores,
        f.descriptors,
        f.image_size,
        type(ex).state_from_arrays({k: np.array(v) for k, v in type(ex).state_arrays(f.dense).items()}),
    )
    pts = np.random.default_rng(0).uniform(5, 200, (64, 2)).astype(np.float32)
    assert np.array_equal(ex.sample(f, pts), ex.sample(back, pts))


def test_map_into_hands_results_in_order_one_chunk_at_a_time():
    from favormap.build import map_into
    from favormap.executor import LocalExecutor

    class Counting(LocalExecutor):
        sizes: list = []

        def map_each(self, fn, tasks, total, sink, gpu=False, progress=None):
            self.sizes.append(total)
            return super().map_each(fn, tasks, total, sink, gpu, progress)

    got, seen = [], []
    ex = Counting()
    map_into(ex, _square, iter(range(7)), 7, lambda i, r: got.append((i, r)), progress=seen.append, chunk=3)
    assert got == [(i, i * i) for i in range(7)] and ex.sizes == [3, 3, 1]
    assert seen == sorted(seen) and seen[-1] == 7


def _square(x, device=None, report=None):
    return x * x


def test_local_executor_hands_each_result_over_while_later_tasks_run():
    """map_each on the thread pool: task 0's result reaches the sink while the last task still waits
    for it (an executor that held every result until all tasks were done would time out here), in
    order, and the executor keeps no result it handed over."""
    import threading
    import weakref

    from favormap.executor import LocalExecutor

    first_sunk = threading.Event()
    refs = []

    class Result:
        def __init__(self, t):
            self.t = t

    def task(t, device=None, report=None):
        if t == 3:  # the last task finishes only once the first result was handed over
            assert first_sunk.wait(10), "the first result was not handed over while the last task ran"
        return Result(t)

    order = []

    def sink(i, r):
        order.append((i, r.t))
        refs.append(weakref.ref(r))
        if i == 0:
            first_sunk.set()

    with LocalExecutor("cpu", workers=2) as ex:
        ex.map_each(task, range(4), 4, sink)
        assert order == [(i, i) for i in range(4)]
        import gc

        gc.collect()
        assert all(ref() is None for ref in refs)  # nothing held by the executor


def test_threaded_cpu_stages_build_the_same_map(small_sequence):
    """LocalExecutor runs extraction and descriptor patches on a pool of threads: the map is the same,
    to the last bit, as with one thread, and the provenance records the pool's size."""
    from favormap.build import build_map
    from favormap.executor import LocalExecutor

    cfg = small_build_config(iterations=20, max_landmarks=150)
    maps = {}
    for workers in (1, 3):
        with LocalExecutor("cpu", workers=workers) as ex:
            maps[workers] = build_map(small_sequence, cfg, executor=ex, feature_cache=False)
    _same_map(maps[1], maps[3])
    assert maps[3].provenance["executor"] == {"name": "local", "device": "cpu", "workers": 3}


def test_local_executor_threads_cpu_tasks_in_order_and_keeps_gpu_tasks_in_the_caller():
    import threading
    import time

    import cv2

    from favormap.executor import LocalExecutor

    def task(t, device=None, report=None):
        time.sleep(0.02 * (5 - t))  # the first tasks finish last
        return t, threading.current_thread().name, device, cv2.getNumThreads()

    from favormap.threads import configure_threads

    done = []
    configure_threads()  # what the executor applies first
    before = cv2.getNumThreads()
    with LocalExecutor("cuda:0", workers=3) as ex:
        out = ex.map(task, range(5), 5, progress=done.append)
        assert [r[0] for r in out] == list(range(5)) and done == [1, 2, 3, 4, 5]
        assert len({r[1] for r in out}) > 1 and all(r[1].startswith("favormap") and r[2] == "cpu" for r in out)
        assert {r[3] for r in out} == {1} and cv2.getNumThreads() == before  # OpenCV serial in the pool only
        gpu = ex.map(task, range(3), 3, gpu=True)
        assert {r[1] for r in gpu} == {threading.current_thread().name} and {r[2] for r in gpu} == {"cuda:0"}

        def fails(t, device=None, report=None):
            if t == 2:
                raise ValueError("task 2 failed")
            return t

        with pytest.raises(ValueError, match="task 2 failed"):
            ex.map(fails, range(4), 4)
    with pytest.raises(ValueError, match="workers"):
        LocalExecutor(workers=0)
