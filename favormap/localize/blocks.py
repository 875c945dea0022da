"""Rendering and matching shared between the localizer's own threads, block by block.

:class:`BlockMatching` is a part of :class:`favormap.localize.Localizer`: it uses the localizer's ``config``,
``source``, ``_helpers`` and ``_pool_lock``. With the pools in the localizer's hands (``LocalizeConfig.threads``;
BLAS then runs each product on its calling thread, favormap.threads.serial_blas) its threads each take the next
block of landmarks, render it where needed and compare it with the query's descriptors: rendering is mostly
memory-bound, the products compute-bound, and the cores stay busy without BLAS's own threads, whose idle
spinning otherwise takes them. The matches are those of describing everything, then matching."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..threads import thread_count
from .descriptors import describe
from .matching import NearestDescriptors, match_descriptors
from .result import Query


class BlockMatching:
    def _pool(self, n: int) -> ThreadPoolExecutor:
        """The localizer's pool of at least ``n`` helper threads (kept between queries: a thread's memory arena
        stays mapped), shared by the threads that localize with it."""
        with self._pool_lock:
            if self._helpers is None or self._helpers._max_workers < n:
                if self._helpers is not None:
                    self._helpers.shutdown(wait=False)
                self._helpers = ThreadPoolExecutor(max(n, 1), thread_name_prefix="favormap-localize")
            return self._helpers

    def _workers(self) -> int:
        """Threads the localizer's own stages may use: with the pools in its hands (``config.threads``; BLAS then
        runs on its calling thread), their size; else 1 (BLAS's own threads parallelize the products)."""
        return thread_count(None) if self.config.threads is not None else 1

    def _describe_and_match(self, q: Query, rows: np.ndarray, pose: np.ndarray, t: dict):
        """(descriptors, their landmark rows, matches): the descriptors of landmarks ``rows`` seen from ``pose``
        (:func:`.descriptors.describe`) matched to the query's (:func:`.matching.match_descriptors`).

        Where the query keeps its descriptors by ray (``q.seen``) and the localizer has several threads
        (:meth:`_workers`), they share the work block by block (:meth:`_match_blocks`), rendering a block
        (``source.chunk`` landmarks) or taking one already described, and matching it. The same matches as
        describing, then matching."""
        cfg = self.config
        workers = self._workers()
        if q.seen is None or workers < 2 or len(rows) == 0:
            rend, drows = describe(self.source, rows, pose, t, q.seen)
            s = time.perf_counter()
            m = match_descriptors(rend, q.desc, cfg.match_threshold, cfg.mutual, cfg.ratio)
            t["matching"] += time.perf_counter() - s
            return rend, drows, m
        kept, kept_desc, fresh, dirs = q.seen.split(rows, pose)
        step = int(getattr(self.source, "chunk", 0) or 0) or max(len(fresh), 1)
        units = [(kept[a : a + 1024], kept_desc[a : a + 1024]) for a in range(0, len(kept), 1024)]
        units += [(fresh[a : a + step], None) for a in range(0, len(fresh), step)]
        described, m = self._match_blocks(
            q, units, len(rows), cfg.mutual, cfg.ratio, lambda at, tm: self.source(rows[at], pose, tm), t
        )
        new = [d for d in described if d is not None]
        rend = np.empty((len(rows), new[0].shape[1] if new else kept_desc.shape[1]), np.float32)
        if len(kept):
            rend[kept] = kept_desc
        if new:
            new = np.concatenate(new)
            rend[fresh] = new
            q.seen.store(rows[fresh], new, dirs[fresh])
        return rend, rows, m

    def _match_blocks(self, q: Query, units: list, n: int, mutual: bool, ratio: float, describe_fn, t: dict):
        """Match ``n`` descriptors, given as ``units`` (positions, descriptors or None: to be described by
        ``describe_fn(positions, timings)``), to the query's on :meth:`_workers` threads, each taking the next
        unit, describing it where needed and comparing it with the query's descriptors
        (:class:`.matching.NearestDescriptors`): rendering is mostly memory-bound, the products compute-bound,
        and the cores stay busy without BLAS's own threads. Returns (each unit's new descriptors or None,
        the matches of :func:`.matching.match_descriptors`)."""
        cfg = self.config
        described: list = [None] * len(units)
        nearest = NearestDescriptors(q.desc, n, second=ratio < 1.0)
        parts = nearest.parts(max(1, min(self._workers(), len(units))))
        times = [dict(loading=0.0, rendering=0.0, matching=0.0) for _ in parts]
        lock, taken = threading.Lock(), iter(range(len(units)))

        def work(k: int):
            while True:
                with lock:
                    i = next(taken, None)
                if i is None:
                    return
                at, d = units[i]
                if d is None:
                    d = describe_fn(at, times[k])
                    if len(d) != len(at):
                        raise ValueError(f"descriptor source {self.source.name!r} gives several per landmark")
                    described[i] = d
                s = time.perf_counter()
                parts[k].add(at, d)
                times[k]["matching"] += time.perf_counter() - s

        jobs = [self._pool(len(parts) - 1).submit(work, k) for k in range(1, len(parts))]
        try:
            work(0)
        finally:
            for job in jobs:
                job.result()
        nearest.join(parts)
        for k in times[0]:  # the threads' times overlap: each stage counts its longest thread's
            t[k] = t.get(k, 0.0) + max(tm[k] for tm in times)
        return described, nearest.matches(cfg.match_threshold, mutual, ratio)
