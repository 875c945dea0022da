"""Executors: who runs the independent tasks of a build stage.

The build's parallel stages (feature extraction per frame, descriptor patches per frame, voxel
training per landmark batch) are lists of independent tasks ``fn(task, device=None, report=None)``
with ``fn`` a module-level function and ``task`` a dataclass. An executor runs them and returns
their results in order; the build code is the same whichever executor runs it:

- :class:`LocalExecutor` (the default): one after the other, in this process;
- :class:`favormap.distributed.RayExecutor`: as Ray tasks on a Ray cluster (``pip install
  favormap[distributed]``), the driver only tracking, triangulating and writing.

``device`` is where an executor puts a task that can use a GPU (the executor decides: the local
executor's own device, or the GPU Ray gave the task); ``report(fraction)`` reports progress inside
one task (a no-op where nobody listens).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

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

    def describe(self) -> dict:
        """What ran the build (recorded in the map's provenance)."""
        return {"name": self.name}

    def close(self) -> None:
        """Release what the executor holds (processes, connections)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LocalExecutor(Executor):
    """Every task in this process, one after the other (torch and OpenCV use their own threads);
    tasks that can use a GPU run on ``device``."""

    name = "local"

    def __init__(self, device: str = "cpu"):
        self.device = device

    def describe(self) -> dict:
        return {"name": self.name, "device": self.device}

    def map(self, fn, tasks, total, gpu=False, progress=None):
        out = []
        for i, t in enumerate(tasks):
            report = (lambda f, i=i: progress(i + f)) if progress else None
            out.append(fn(t, device=self.device if gpu else "cpu", report=report))
            if progress:
                progress(i + 1)
        return out
