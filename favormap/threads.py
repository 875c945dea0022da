"""Thread pools sized to the CPUs this process may actually use, and that nothing else is using.

Several favormap processes on one machine (two builds, a localizer beside a build, parallel CI
jobs, Ray workers) must not slow each other down. torch (OpenMP, libgomp) and OpenCV (pthreads)
size their pools to every core of the machine and OpenMP threads spin while they wait for work, so
two processes that each take every core fight over them (tools/bench_load.py measures it).

The rule (:func:`resolve_threads`), applied at the start of every heavy command of the CLI, and by the
Python API only when asked (``threads="auto"`` or a count in ``BuildConfig`` / ``LocalizeConfig``;
:func:`thread_count`): a program that embeds favormap keeps its own pool sizes otherwise.

1. an explicit count (``--threads N``, ``threads=`` in the Python API) wins;
2. else ``OMP_NUM_THREADS`` when it is set to a positive integer;
3. else the CPUs this process may use, its CPU affinity (``os.sched_getaffinity``) capped by the
   cgroup CPU quota (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us / cpu.cfs_period_us``), less the CPUs
   other processes kept busy (from ``/proc/stat``, the affinity CPUs only, this process's own time
   taken out) since this module was imported (at least :data:`MIN_WINDOW_S`; a fresh measurement
   when that was more than :data:`MAX_WINDOW_S` ago), rounded, at least 1.
   Long commands re-apply it every few seconds (:func:`rebalance`, from the build's progress), so a
   build gives back a core when a second one starts and takes it again when that one ends.

An instantaneous measurement rather than the load average: the 1-minute load average lags by tens
of seconds, so two commands started together would both see an idle machine.

:func:`configure_threads` then sets torch's intra-op pool (``torch.set_num_threads``, which also
sets OpenMP's and MKL's), torch's inter-op pool to 1 (favormap never runs independent torch ops in
parallel; that pool only adds idle threads) and OpenCV's pool (``cv2.setNumThreads``).
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError

_applied: int | None = None  # thread count set by the last configure_threads call


def _cgroup_quota(root: Path = Path("/sys/fs/cgroup"), proc_cgroup: Path = Path("/proc/self/cgroup")) -> float | None:
    """CPUs allowed by the cgroup CPU quota of this process (None: no quota found)."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        lines = []
    v2_rel, v1_rel = None, None
    for ln in lines:
        parts = ln.split(":", 2)
        if len(parts) != 3:
            continue
        if parts[0] == "0" and parts[1] == "":
            v2_rel = parts[2]
        elif "cpu" in parts[1].split(","):
            v1_rel = parts[2]
    candidates = []
    if v2_rel is not None:  # cgroup v2: "max 100000" or "200000 100000", checked up the hierarchy
        rel = Path(v2_rel.lstrip("/"))
        for d in [root / rel, *[root / p for p in rel.parents]]:
            candidates.append(("v2", d / "cpu.max"))
    for base in (root / "cpu", root / "cpu,cpuacct", root / "cpuacct,cpu"):
        rels = [Path(v1_rel.lstrip("/"))] if v1_rel else []
        for rel in rels + [Path(".")]:
            candidates.append(("v1", base / rel))
    best = None
    for kind, p in candidates:
        try:
            if kind == "v2":
                quota, period = p.read_text().split()[:2]
                if quota == "max":
                    continue
                cpus = int(quota) / int(period)
            else:
                quota = int((p / "cpu.cfs_quota_us").read_text())
                period = int((p / "cpu.cfs_period_us").read_text())
                if quota <= 0 or period <= 0:
                    continue
                cpus = quota / period
        except (OSError, ValueError):
            continue
        if cpus > 0:
            best = cpus if best is None else min(best, cpus)
    return best


def available_cpus() -> int:
    """CPUs this process may use: affinity mask capped by the cgroup quota, at least 1."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        n = os.cpu_count() or 1
    quota = _cgroup_quota()
    if quota is not None:
        n = min(n, max(1, math.floor(quota)))
    return max(1, n)


MIN_WINDOW_S = 0.3  # shortest window over which other processes' CPU use is measured
MAX_WINDOW_S = 10.0  # an older starting sample is replaced by a fresh MIN_WINDOW_S measurement
REBALANCE_S = 3.0  # rebalance() re-measures at most this often


def _affinity() -> set[int] | None:
    try:
        return set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


class _Sample:
    """Busy CPU seconds of the affinity CPUs (/proc/stat), this process's CPU seconds, and the time."""

    def __init__(self):
        self.t = time.monotonic()
        tm = os.times()
        self.own = tm.user + tm.system
        self.busy = _busy_seconds(_affinity())


def _busy_seconds(cpus: set[int] | None) -> float | None:
    """CPU seconds the given CPUs spent busy since boot (user, nice, system, irq, softirq, steal)."""
    try:
        lines = Path("/proc/stat").read_text().splitlines()
    except OSError:
        return None
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    total = 0
    found = False
    for ln in lines:
        if not ln.startswith("cpu") or ln.startswith("cpu "):
            continue
        parts = ln.split()
        try:
            cpu = int(parts[0][3:])
            v = [int(x) for x in parts[1:9]]
        except (ValueError, IndexError):
            continue
        if cpus is not None and cpu not in cpus:
            continue
        user, nice, system, _idle, _iowait, irq, softirq, steal = v + [0] * (8 - len(v))
        total += user + nice + system + irq + softirq + steal
        found = True
    return total / hz if found else None


def others_busy(since: _Sample, now: _Sample) -> float | None:
    """CPUs (of this process's affinity) that other processes kept busy between two samples."""
    dt = now.t - since.t
    if since.busy is None or now.busy is None or dt <= 0:
        return None
    return max(0.0, (now.busy - since.busy - (now.own - since.own)) / dt)


_start = _Sample()  # at import: the CLI imports this module first, so the window spans its imports
_lock = threading.Lock()
_torch_sized = False  # torch's pools were sized (torch is imported only by the commands that need it)
_serial = 0  # open serial_pools() blocks: OpenCV's, torch's and BLAS's pools stay at one thread meanwhile
_blas_limits = None  # threadpoolctl's limit while a serial_pools() or serial_blas() block is open
_blas_holds = 0  # open serial_pools() and serial_blas() blocks
_saved: tuple = (1, None)  # OpenCV's and torch's pool sizes when the outermost serial_pools() block began
_auto = False  # the applied count came from rule 3 (rebalance() may change it)
_last: _Sample = _start


def _free_cpus(since: _Sample) -> tuple[int, _Sample]:
    if time.monotonic() - since.t > MAX_WINDOW_S:  # the load long ago says little about now
        since = _Sample()
    wait = MIN_WINDOW_S - (time.monotonic() - since.t)
    if wait > 0:
        time.sleep(wait)
    now = _Sample()
    cap = available_cpus()
    busy = others_busy(since, now)
    if busy is None:  # no /proc/stat: the CPUs we may use
        return cap, now
    return max(1, min(cap, int(math.floor(cap - busy + 0.5)))), now


def _env_threads() -> int | None:
    v = os.environ.get("OMP_NUM_THREADS", "").strip()
    if not v:
        return None
    try:
        n = int(v.split(",")[0])  # OpenMP allows a nesting list "4,2": the outer level counts
    except ValueError:
        return None
    return n if n > 0 else None


def resolve_threads(threads: int | None = None) -> int:
    """Thread count by the rule of this module: ``threads`` > ``OMP_NUM_THREADS`` > the usable CPUs
    that other processes leave free (measured since this module was imported)."""
    return _resolve(threads)[0]


def _resolve(threads):
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise InputError(f"threads must be a positive integer, got {threads!r}")
        return threads, False, None
    env = _env_threads()
    if env:
        return env, False, None
    n, now = _free_cpus(_start)
    return n, True, now


def thread_count(threads: int | str | None = None) -> int:
    """The thread count a library call sizes its own worker pools by, applying ``threads`` to the process's
    pools only when given. None leaves torch's and OpenCV's pools as they are and returns the count configured
    earlier in this process, else ``OMP_NUM_THREADS``, else the CPUs this process may use (no load measurement);
    "auto" applies the rule (:func:`configure_threads`), a number that count."""
    if threads is None:
        return _applied if _applied is not None else (_env_threads() or available_cpus())
    if threads == "auto":
        return configure_threads(None)
    return configure_threads(threads)


def configure_threads(threads: int | None = None) -> int:
    """Size torch's and OpenCV's thread pools by :func:`resolve_threads`; returns the count.

    Call it once at the start of a heavy command (the CLI does; ``build_map`` and ``Localizer`` when their
    ``threads`` is given).
    ``threads=None`` applies the rule the first time and afterwards keeps what was configured; an
    explicit count resizes the pools when it differs from the current one."""
    global _applied, _auto, _last
    with _lock:
        if threads is None and _applied is not None:
            if not _torch_sized and "torch" in sys.modules:  # torch was imported since: size its pool too
                _set_pools(_applied, first=False)
            return _applied

        n, auto, now = _resolve(threads)
        _set_pools(n, first=_applied is None)
        _applied, _auto = n, auto
        if now is not None:
            _last = now
        return n


def rebalance() -> int | None:
    """Re-apply rule 3 when it chose the current count and :data:`REBALANCE_S` have passed since the
    last measurement: a long command calls this from its progress reports. Returns the count."""
    global _applied, _last
    if not _auto or time.monotonic() - _last.t < REBALANCE_S:
        return _applied
    with _lock:
        if not _auto:
            return _applied
        n, now = _free_cpus(_last)
        _last = now
        if n != _applied:
            _set_pools(n, first=False)
            _applied = n
        return n


def _set_pools(n: int, first: bool) -> None:
    """Size OpenCV's pool, and torch's when torch is loaded: a command that never needs torch (a
    one-shot localization against a SIFT map) does not pay its ~2 s import; one that imports it
    later gets the count when it calls :func:`configure_threads` again."""
    global _torch_sized
    torch = sys.modules.get("torch")
    if torch is not None:
        if torch.get_num_threads() != n and not _serial:  # a serial_pools() block sizes it on leaving
            torch.set_num_threads(n)
        if first or not _torch_sized:
            try:
                torch.set_num_interop_threads(1)
            except RuntimeError:  # inter-op pool already started (set by the caller or used): leave it
                pass
        _torch_sized = True
    if _serial:  # a pool of Python threads runs OpenCV calls: its pool is sized on leaving
        return
    try:
        import cv2

        cv2.setNumThreads(n)
    except ImportError:  # pragma: no cover - opencv is a core dependency
        pass


@contextmanager
def serial_pools():
    """OpenCV, torch and NumPy's BLAS run each call in its calling thread while the block runs
    (``cv2.setNumThreads(1)``, ``torch.set_num_threads(1)`` when torch is loaded, threadpoolctl's
    BLAS limit), for a pool of Python threads that each run such calls (favormap.executor.LocalExecutor,
    the tracking's frame pairs): one core per thread. OpenCV runs a call serially while its pool is
    busy with another thread's, so that call's share of the cores idled; a torch call from another
    thread than the one that sized torch's pool starts an OpenMP team of its own, and once the threads
    of all teams outnumber the cores, libgomp stops spinning between parallel regions, so torch ran
    slower for the rest of the process (fox: the build's training 2.0 -> 3.0 s, system time doubled,
    after one float16 conversion per patch task on two threads). A resize by the rule meanwhile
    (configure_threads, rebalance) takes effect on leaving; nested blocks restore when the last one ends."""
    global _serial, _saved
    import cv2

    with _lock:
        _serial += 1
        _hold_blas()
        if _serial == 1:  # first: it records the limits it changes to restore them
            torch = sys.modules.get("torch")
            # the sizes to restore when nobody configured the pools (favormap.threads leaves them alone then)
            _saved = (cv2.getNumThreads(), torch.get_num_threads() if torch is not None else None)
        cv2.setNumThreads(1)
        torch = sys.modules.get("torch")
        if torch is not None and torch.get_num_threads() != 1:
            torch.set_num_threads(1)
    try:
        yield
    finally:
        with _lock:
            _serial -= 1
            _release_blas()  # first: threadpoolctl restores OpenMP's count of this thread too
            if not _serial:
                n_cv, n_torch = (_applied, _applied) if _applied is not None else _saved
                cv2.setNumThreads(n_cv)
                torch = sys.modules.get("torch")
                if torch is not None and n_torch is not None:  # (torch imported inside the block: left as it is)
                    # always: torch.get_num_threads() reads OpenMP's count, which threadpoolctl may have
                    # restored behind torch's back, while torch's MKL stayed at one thread (the training
                    # after a pool would run its products on one core)
                    torch.set_num_threads(n_torch)


@contextmanager
def serial_blas():
    """NumPy's and OpenCV's BLAS run each call in its calling thread while the block runs (threadpoolctl's
    limit), for code that runs its stages on threads of its own (the localizer: rendering on one core while
    the products run on another). OpenBLAS's idle threads keep spinning for ~0.1 s after each product,
    taking those cores from the other stages (a third of a localizing process's CPU time on 2 cores,
    tools/bench_localize.py). Blocks may nest and overlap (threads sharing a localizer); the limit is
    given back when the last one ends."""
    with _lock:
        _hold_blas()
    try:
        yield
    finally:
        with _lock:
            _release_blas()


def _hold_blas() -> None:
    """Hold the BLAS libraries at one thread (under ``_lock``; counted: :func:`_release_blas` gives it back)."""
    global _blas_holds, _blas_limits
    _blas_holds += 1
    if _blas_holds == 1:
        try:
            from threadpoolctl import threadpool_limits
        except ImportError:  # a dependency, but a copied tree (tools/gpu_check.sh) may run without it
            threadpool_limits = None
        _blas_limits = threadpool_limits(1, user_api="blas") if threadpool_limits else None


def _release_blas() -> None:
    global _blas_holds, _blas_limits
    _blas_holds -= 1
    if not _blas_holds and _blas_limits is not None:
        _blas_limits.restore_original_limits()
        _blas_limits = None


def _positive_int(s: str) -> int:
    import argparse

    try:
        n = int(s)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {s!r}")
    return n


def add_threads_arg(parser) -> None:
    """``--threads N`` for a heavy CLI command."""
    parser.add_argument(
        "--threads",
        type=_positive_int,
        metavar="N",
        default=None,
        help="CPU threads for torch/OpenCV (default: OMP_NUM_THREADS when set, else the CPUs this "
        "process may use (affinity, cgroup quota) that other processes leave free)",
    )
