"""Distributed builds on a Ray cluster (``pip install favormap[distributed]``).

:class:`RayExecutor` runs the build's independent tasks (feature extraction per frame, descriptor
patches per frame, voxel training per landmark batch: see :mod:`favormap.executor`) as Ray tasks;
the driver (the ``favormap build`` process) only reads the image files, tracks, triangulates and
writes the map. The task functions are the very ones the single-process build runs, so the map is
the same up to floating-point noise (training batches are seeded per batch, not per worker).

- ``address``: "auto" connects to the cluster of ``RAY_ADDRESS`` or one started on this machine
  with ``ray start``, else starts a local instance with every core; "local" always starts a local
  instance; anything else is a cluster address (``HOST:6379``, ``ray://HOST:10001``).
- A task whose worker process dies (killed, out of memory, machine lost) is re-run by Ray up to
  ``max_retries`` times; a task that still fails ends the build with one error and no map is
  written (the map file is written by the driver, atomically, after every task has succeeded).
- Tasks take ``cpus_per_task`` CPUs (their torch/OpenCV threads are set to that) and, where the
  cluster has GPUs and ``gpus`` allows, one GPU each for training (and for extractors that run on
  torch); the device of a task is then the GPU Ray gave it.
- Nothing phones home: Ray's usage statistics are switched off (``RAY_USAGE_STATS_ENABLED=0``) and
  a local instance starts without its dashboard.
"""

from __future__ import annotations

import hashlib
import os
import socket
from collections import deque
from functools import lru_cache

from .errors import FavormapError, InputError, first_line
from .executor import Executor

INSTALL_HINT = "pip install 'favormap[distributed]'"


def import_ray():
    """The ``ray`` module, or one clear error saying how to install it."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"  # before ray is imported: nothing phones home
    try:
        import ray
    except ImportError:
        raise InputError(f"--ray needs Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _set_threads(n: int) -> None:
    """torch/OpenCV pools of this worker = the CPUs Ray gave the task (an explicit count: see favormap.threads)."""
    from .threads import configure_threads

    configure_threads(max(1, n))


_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of favormap's Python sources (driver and workers must run the same code)."""
    h = hashlib.sha1()
    for root, dirs, files in sorted(os.walk(_PACKAGE_DIR)):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(root, name)
                h.update(os.path.relpath(path, _PACKAGE_DIR).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


def _run(fn, task, use_gpu: bool, fingerprint: str):
    """Body of every Ray task: same code as the driver's, threads and device from the resources Ray
    assigned to this task."""
    import ray

    if code_fingerprint() != fingerprint:
        raise FavormapError(
            f"a Ray worker on {socket.gethostname()} runs other favormap code ({_PACKAGE_DIR}) than "
            "this driver: install the same favormap version on every machine"
        )
    res = ray.get_runtime_context().get_assigned_resources()
    _set_threads(int(res.get("CPU", 1)))
    device = "cuda" if use_gpu and ray.get_gpu_ids() else "cpu"
    return fn(task, device=device)


class RayExecutor(Executor):
    """Build tasks as Ray tasks. ``gpus``: let tasks that can use a GPU ask for one where the
    cluster has GPUs (False: CPU only, e.g. ``--device cpu``). At most ``max_in_flight`` tasks are
    submitted at a time (default: 2 per CPU of the cluster), so the image bytes and patches waiting
    in the object store stay bounded. ``num_cpus``: CPUs of a local instance this starts (default:
    every core). An executor that starts or joins Ray shuts its connection down on :meth:`close`;
    one created where Ray is already initialised uses that connection and leaves it open."""

    name = "ray"

    def __init__(
        self,
        address: str = "auto",
        cpus_per_task: float = 1,
        gpus: bool = True,
        max_retries: int = 3,
        max_in_flight: int | None = None,
        num_cpus: int | None = None,
    ):
        if cpus_per_task <= 0:
            raise InputError(f"cpus per Ray task must be > 0, not {cpus_per_task}")
        if max_retries < 0:
            raise InputError(f"Ray task retries must be >= 0, not {max_retries}")
        ray = self.ray = import_ray()
        self.address = address
        self._owns = not ray.is_initialized()
        self.context = None  # what ray.init returned, when this executor started or joined Ray
        if self._owns:
            # the driver's favormap code goes to the workers with the job (Ray caches it by content),
            # so worker machines need favormap's dependencies, not favormap itself
            kw = dict(
                include_dashboard=False,
                logging_level="WARNING",
                log_to_driver=False,
                runtime_env={"py_modules": [_PACKAGE_DIR], "excludes": ["__pycache__/"]},
            )
            if address not in ("auto", "local"):
                kw.pop("include_dashboard")  # a setting of the cluster, not of a driver joining it
            elif num_cpus is not None:
                kw["num_cpus"] = int(num_cpus)
            # Ray's C++ client logs every failed connection attempt on stderr: keep that for the message
            with _captured_stderr() as log:
                try:
                    self.context = ray.init(**({} if address == "auto" else {"address": address}), **kw)
                except Exception as e:  # noqa: BLE001 - Ray raises plain Exceptions too (e.g. a node start-up timeout)
                    err = e
                else:
                    err = None
            if err is not None:
                hint = ""
                if "InvalidAuthToken" in log.text:
                    hint = (
                        " (the cluster refused this machine's token: set RAY_AUTH_MODE=token and the cluster's"
                        " RAY_AUTH_TOKEN)"
                    )
                what = (
                    "start a local Ray instance" if address == "local" else f"connect to the Ray cluster at {address!r}"
                )
                raise FavormapError(f"cannot {what}: {first_line(err)}{hint}") from None
        res = ray.cluster_resources()
        self.cluster_cpus = float(res.get("CPU", 0))
        self.cluster_gpus = float(res.get("GPU", 0))
        if self.cluster_cpus < cpus_per_task:
            raise FavormapError(
                f"the Ray cluster has {self.cluster_cpus:g} CPUs, fewer than one task needs ({cpus_per_task:g})"
            )
        self.cpus_per_task = cpus_per_task
        self.use_gpus = bool(gpus) and self.cluster_gpus >= 1
        self.max_retries = int(max_retries)
        self.max_in_flight = max_in_flight or max(2, int(2 * self.cluster_cpus / cpus_per_task))
        self._fingerprint = code_fingerprint()
        self._remote = ray.remote(_run)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "address": self.address,
            "nodes": len([n for n in self.ray.nodes() if n.get("Alive")]),
            "cpus": self.cluster_cpus,
            "gpus": self.cluster_gpus,
            "cpus_per_task": self.cpus_per_task,
            "gpu_tasks": self.use_gpus,
        }

    @property
    def has_gpu(self) -> bool:
        return self.use_gpus

    def map(self, fn, tasks, total, gpu=False, progress=None):
        ray = self.ray
        use_gpu = gpu and self.use_gpus
        remote = self._remote.options(
            num_cpus=self.cpus_per_task,
            num_gpus=1 if use_gpu else 0,
            max_retries=self.max_retries,
            retry_exceptions=False,
            name=f"favormap.{fn.__name__}",
        )
        refs, index = [], {}
        pending: deque = deque()
        results: list = [None] * total
        done = 0
        it = iter(tasks)
        try:
            while True:
                while len(pending) < self.max_in_flight:
                    t = next(it, None)
                    if t is None:
                        break
                    ref = remote.remote(fn, t, use_gpu, self._fingerprint)
                    index[ref] = len(refs)
                    refs.append(ref)
                    pending.append(ref)
                if not pending:
                    break
                ready, rest = ray.wait(list(pending), num_returns=1)
                pending = deque(rest)
                for ref in ready:
                    results[index.pop(ref)] = ray.get(ref)
                    done += 1
                    if progress:
                        progress(done)
        except BaseException as e:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise _translate(e, fn.__name__, self.max_retries) from None
        if len(refs) != total:
            raise FavormapError(f"internal: {len(refs)} Ray tasks for {total} expected")
        return results

    def close(self) -> None:
        if self._owns and self.ray.is_initialized():
            self.ray.shutdown()
        self._owns = False


class _captured_stderr:
    """File descriptor 2 into a temporary file while in the block (C++ logging included); ``text``
    holds what was written."""

    def __enter__(self):
        import sys
        import tempfile

        sys.stderr.flush()
        self._tmp = tempfile.TemporaryFile()
        self._saved = os.dup(2)
        os.dup2(self._tmp.fileno(), 2)
        self.text = ""
        return self

    def __exit__(self, *exc):
        import sys

        sys.stderr.flush()
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._tmp.seek(0)
        self.text = self._tmp.read().decode(errors="replace")
        self._tmp.close()


def _translate(e: BaseException, what: str, retries: int) -> BaseException:
    """A Ray failure as the build's own error (one line), the task's own errors unchanged."""
    from ray import exceptions as rex

    if isinstance(e, rex.RayTaskError):
        cause = getattr(e, "cause", None)
        if isinstance(cause, FavormapError):
            return cause
        return FavormapError(f"Ray task {what} failed: {first_line(cause) if cause else first_line(e)}")
    if isinstance(e, (rex.WorkerCrashedError, rex.NodeDiedError, rex.ObjectLostError, rex.OwnerDiedError)):
        return FavormapError(
            f"a Ray worker running {what} died and the task failed after {retries} retries ({type(e).__name__})"
        )
    if isinstance(e, rex.RayError):
        return FavormapError(f"Ray failed running {what}: {first_line(e)}")
    return e
