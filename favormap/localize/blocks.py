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
from .matching import NearestDescriptors, distinct_pairs, match_descriptors, pair_similarity
from .result import Query


class BlockMatching:
    def _pool(self, n: int) -> ThreadPoolExecutor:
        """The localizer's pool of helper threads (``n``, or one fewer than :meth:`_workers` if more, when first
        asked for; kept between queries), shared by the threads that localize with it. A caller works through its
        own units too, so a job that waits for a busy or smaller pool only finds fewer left."""
        with self._pool_lock:
            if self._helpers is None:
                size = max(n, self._workers() - 1, 1)
                self._helpers = ThreadPoolExecutor(size, thread_name_prefix="favormap-localize")
            return self._helpers

    def _workers(self) -> int:
        """Threads the localizer's own stages may use: with the pools in its hands (``config.threads``; BLAS then
        runs on its calling thread), their size; else 1 (BLAS's own threads parallelize the products)."""
        return thread_count(None) if self.config.threads is not None else 1

    def _describe_and_match(self, q: Query, rows: np.ndarray, pose: np.ndarray, t: dict):
        """(each descriptor's landmark row, matches, their cosines): the descriptors of landmarks ``rows`` seen
        from ``pose`` (:func:`.descriptors.describe`) matched to the query's (:func:`.matching.match_descriptors`,
        a landmark-keypoint pair once: :func:`.matching.distinct_pairs`).

        Where the query keeps its descriptors by ray (``q.seen``) and the localizer has several threads
        (:meth:`_workers`), they share the work block by block (:meth:`_match_blocks`), rendering a block
        (``source.chunk`` landmarks) or taking one already described, and matching it. The same matches as
        describing, then matching."""
        cfg = self.config
        if q.seen is None or self._workers() < 2 or len(rows) == 0:
            rend, drows = describe(self.source, rows, pose, t, q.seen)
            s = time.perf_counter()
            m = match_descriptors(rend, q.desc, cfg.match_threshold, cfg.mutual, cfg.ratio)
            m = distinct_pairs(m, drows, len(rows))
            sims = pair_similarity(rend, q.desc, m)
            t["matching"] += time.perf_counter() - s
            return drows, m, sims
        seen, source = q.seen, self.source
        kept, slots, fresh, dirs = seen.split(rows, pose)
        step = int(getattr(source, "chunk", 0) or 0) or max(len(fresh), 1)
        units = [(kept[a : a + 1024], slots[a : a + 1024]) for a in range(0, len(kept), 1024)]
        units = [(at, lambda tm, s=s: seen.desc[s]) for at, s in units]
        n_kept = len(units)
        for a in range(0, len(fresh), step):
            at = fresh[a : a + step]
            units.append((at, lambda tm, at=at: self._described(source, rows[at], pose, tm)))
        described, m, sims = self._match_blocks(q, units, len(rows), cfg.mutual, cfg.ratio, t)
        new = described[n_kept:]
        if new:
            seen.store(rows[fresh], np.concatenate(new), dirs[fresh])
        return rows, m, sims

    def _match_all(self, q: Query, d: np.ndarray, mutual: bool, ratio: float, t: dict) -> np.ndarray:
        """:func:`.matching.match_descriptors` of descriptors ``d`` to the query's, on the localizer's threads
        where it has several (:meth:`_match_blocks`)."""
        if self._workers() > 1:
            units = [
                (np.arange(a, min(a + 1024, len(d))), lambda tm, a=a: d[a : a + 1024]) for a in range(0, len(d), 1024)
            ]
            return self._match_blocks(q, units, len(d), mutual, ratio, t)[1]
        s = time.perf_counter()
        m = match_descriptors(d, q.desc, self.config.match_threshold, mutual, ratio)
        t["matching"] += time.perf_counter() - s
        return m

    def _described(self, source, rows: np.ndarray, pose: np.ndarray, timings: dict) -> np.ndarray:
        d = source(rows, pose, timings)
        if len(d) != len(rows):
            raise ValueError(f"descriptor source {getattr(source, 'name', source)!r} gives several per landmark")
        return d

    def _match_blocks(self, q: Query, units: list, n: int, mutual: bool, ratio: float, t: dict):
        """Match ``n`` descriptors, given as ``units`` (positions, ``get(timings)`` -> their descriptors), to the
        query's on :meth:`_workers` threads, each taking the next unit, getting its descriptors (rendering them,
        where it renders) and comparing them with the query's (:class:`.matching.NearestDescriptors`): rendering
        is mostly memory-bound, the products compute-bound, and the cores stay busy without BLAS's own threads.
        Returns (each unit's descriptors, the matches of :func:`.matching.match_descriptors`, their cosines)."""
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
                at, get = units[i]
                described[i] = d = get(times[k])
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
        m = nearest.matches(cfg.match_threshold, mutual, ratio)
        return described, m, nearest.best_sim[m[:, 0]]
