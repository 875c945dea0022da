"""Executors: who runs the independent tasks of a build stage.

The build's parallel stages (feature extraction per frame, descriptor patches per frame, voxel
training per landmark batch) are lists of independent tasks ``fn(task, device=None, report=None)``
with ``fn`` a module-level function and ``task`` a dataclass. An executor runs them and returns
their results in order; the build code is the same whichever executor runs it:

- :class:`LocalExecutor` (the default): in this process, CPU-only tasks on a pool of threads;
- :class:`favormap.distributed.RayExecutor`: as Ray tasks on a Ray cluster (``pip install
  favormap[distributed]``), the driver only tracking, triangulating and writing.

``device`` is where an executor puts a task that can use a GPU (the executor decides: the local
executor's own device, or the GPU Ray gave the task); ``report(fraction)`` reports progress inside
one task (a no-op where nobody listens).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor

TaskFn = Callable[..., object]


class Executor:
    """Runs lists of independent tasks; subclasses implement :meth:`map`."""

    name = "executor"

    def map(
        self,
        fn: TaskFn,
        tasks: Iterable,
        total: int,
        gpu: bool = False,
        progress: Callable[[float], None] | None = None,
    ) -> list:
        """``[fn(t) for t in tasks]`` (``total`` of them), in order. ``gpu``: the task can use a
        GPU. ``progress(done)`` is called with the number of tasks done (fractional while one runs)."""
        raise NotImplementedError

    def map_each(
        self,
        fn: TaskFn,
        tasks: Iterable,
        total: int,
        sink: Callable[[int, object], None],
        gpu: bool = False,
        progress: Callable[[float], None] | None = None,
    ) -> None:
        """``sink(i, fn(task_i))`` for every task, in order. An executor that can hands each result
        over as soon as it and those before it are done, and keeps none (:class:`LocalExecutor`);
        by default, after :meth:`map`."""
        for i, r in enumerate(self.map(fn, tasks, total, gpu=gpu, progress=progress)):
            sink(i, r)

    def describe(self) -> dict:
        """What ran the build (recorded in the map's provenance)."""
        return {"name": self.name}

    @property
    def has_gpu(self) -> bool:
        """Whether tasks that can use a GPU (``map(..., gpu=True)``) get one."""
        return False

    def train_group(self) -> int:
        """How many consecutive training batches one task may train together (the same grids
        either way): 1, except on a local GPU, where fewer, larger steps are faster."""
        return 1

    def close(self) -> None:
        """Release what the executor holds (processes, connections)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalExecutor(Executor):
    """Every task in this process. Tasks that can use a GPU run one after the other on ``device``
    (torch uses its own threads); CPU-only tasks (SIFT extraction, descriptor patches) run on a pool
    of ``workers`` threads (OpenCV releases the GIL; its own pool is held at one thread meanwhile,
    favormap.threads.serial_pools, so each thread has one core; torch's too). ``workers`` None:
    favormap.threads.thread_count() (what the process configured, else its CPUs); 1: one after the other.

    Results are the same whatever the worker count (tests/test_feature_cache.py): each task is a
    pure function of its input and results are returned in task order. Measured on 16 cores (H200
    machine, fox at full resolution, tools/bench_build.py): extraction 8.7 s serial -> 2.3 s on 16
    threads; descriptor patches 10.6 / 11.8 s serial on OpenCV's pool -> 8.4 s (quick preset: 7.5 ->
    3.1 s), OpenCV's per-call pyramid being the part its pool does not spread."""

    name = "local"

    def __init__(self, device: str = "cpu", workers: int | None = None):
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a positive integer or None, got {workers!r}")
        self.device = device
        self.workers = workers
        self._pool: ThreadPoolExecutor | None = None
        self._pool_size = 0

    def describe(self) -> dict:
        return {"name": self.name, "device": self.device, "workers": self._workers()}

    @property
    def has_gpu(self) -> bool:
        return str(self.device) != "cpu"

    def train_group(self) -> int:
        # a GPU's training steps are bound by kernel launches, not arithmetic, so several batches train
        # faster as one task (docs/measurements.md, "On a GPU"); 16 batches of 1,024 landmarks keep a
        # task's training data at a few GB
        return 16 if self.has_gpu else 1

    def _workers(self) -> int:
        if self.workers is not None:
            return self.workers
        from .threads import thread_count

        return thread_count()

    def map(self, fn, tasks, total, gpu=False, progress=None):
        out: list = []
        self.map_each(fn, tasks, total, lambda i, r: out.append(r), gpu, progress)
        return out

    def map_each(self, fn, tasks, total, sink, gpu=False, progress=None):
        n = 1 if gpu else min(self._workers(), total)
        if n <= 1:
            for i, t in enumerate(tasks):
                report = (lambda f, i=i: progress(i + f)) if progress else None
                sink(i, fn(t, device=self.device if gpu else "cpu", report=report))
                if progress:
                    progress(i + 1)
            return
        if self._pool is None or self._pool_size != n:
            self.close()
            self._pool, self._pool_size = ThreadPoolExecutor(n, thread_name_prefix="favormap"), n
        from .threads import serial_pools

        with serial_pools():  # one core per thread (see there)
            futures = [self._pool.submit(fn, t, device="cpu") for t in tasks]
            try:
                for i in range(len(futures)):
                    # handed over while later tasks run, then dropped: a stage's results are not all
                    # held at once (fox patches: 260 MB less at the peak, and the sink's copies overlap)
                    r, futures[i] = futures[i].result(), None
                    sink(i, r)
                    del r
                    if progress:
                        progress(i + 1)
            except BaseException:
                for f in futures:
                    if f is not None:
                        f.cancel()
                raise

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._pool_size = None, 0
