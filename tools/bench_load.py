#!/usr/bin/env python3
"""favormap under load: several processes (or threads) on one machine.

    PYTHONPATH=. python3 tools/bench_load.py [--sequence SEQ] [--sections a,b,c] [--builds 1,2,4]
                                              [--clients 1,2,4,8] [--queries 24] [--threads N]

(a) N = 1, 2, 4 concurrent ``favormap build`` runs of a small sequence (default
    ../shared/data/llff_fern, else a synthetic room): total wall time against the same N runs one
    after the other, and the CPU seconds they used (spinning threads show up there);
(b) K = 1, 2, 4, 8 concurrent localization clients of one map: K processes (each its own
    Localizer), then K threads sharing one Localizer through the Python API: queries/s, p50/p99
    latency of one query, peak RSS (per process; the threads share one);
(c) reader processes localizing one map while ``favormap prune`` and ``favormap merge`` write new
    maps beside it in the same folder: reader throughput and failures, and whether the written maps
    validate.

Every figure is measured on this machine; the header prints its CPUs and load average (other work
running at the same time slows every row, so rerun it on an idle machine for reference figures).
``--threads`` is passed to every favormap command and Localizer (default: favormap's rule).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), RERUN_ANALYTICS="false")


def _loadavg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _favormap(*args: str, threads: int | None) -> list[str]:
    return [sys.executable, "-m", "favormap", *args] + (["--threads", str(threads)] if threads else [])


def _run_many(cmds: list[list[str]], concurrent: bool) -> tuple[float, float]:
    """Run commands together or one after the other: (wall seconds, CPU seconds of all of them)."""
    t0 = time.perf_counter()
    cpu = 0.0
    batches = [cmds] if concurrent else [[c] for c in cmds]
    for batch in batches:
        procs = [subprocess.Popen(c, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for c in batch]
        for p in procs:
            _, status, ru = os.wait4(p.pid, 0)
            p.returncode = os.waitstatus_to_exitcode(status)
            cpu += ru.ru_utime + ru.ru_stime
            if p.returncode != 0:
                raise SystemExit(
                    f"bench_load: {' '.join(c for c in p.args[2:])} failed: {p.stderr.read().decode()[-500:]}"
                )
            p.stderr.close()
    return time.perf_counter() - t0, cpu


# -- (a) concurrent builds -----------------------------------------------------------------------------
def bench_builds(seq: Path, work: Path, counts: list[int], threads: int | None) -> list[dict]:
    rows = []
    for n in counts:
        cmds = [_favormap("build", str(seq), "-o", str(work / f"build{i}.h5"), "-q", threads=threads) for i in range(n)]
        seq_wall, seq_cpu = _run_many(cmds, concurrent=False)
        load = _loadavg()
        con_wall, con_cpu = _run_many(cmds, concurrent=True)
        rows.append(
            {
                "n": n,
                "sequential_s": seq_wall,
                "concurrent_s": con_wall,
                "ratio": con_wall / seq_wall,
                "cpu_sequential_s": seq_cpu,
                "cpu_concurrent_s": con_cpu,
                "load": load,
            }
        )
        print(
            f"  N={n}: sequential {seq_wall:6.1f} s (cpu {seq_cpu:6.1f} s)   concurrent {con_wall:6.1f} s "
            f"(cpu {con_cpu:6.1f} s)   ratio {con_wall / seq_wall:.2f}   load {load}",
            flush=True,
        )
    return rows


# -- (b) localization clients ----------------------------------------------------------------------------
CLIENT = r"""
import json, resource, sys, time
sys.path.insert(0, sys.argv[1])
from tools.bench_load import load_queries, localize_all
spec = json.loads(sys.argv[2])
from favormap.localize import Localizer, LocalizeConfig
loc = Localizer(spec["map"], LocalizeConfig(threads=spec["threads"] or "auto"))
queries = load_queries(spec["queries"])
localize_all(loc, queries[:1], 1)  # warm-up (first-call allocations, global descriptors)
print("ready", flush=True)
sys.stdin.readline()  # start signal
lat, ok = localize_all(loc, queries, spec["n"])
print(json.dumps({"lat": lat, "ok": ok, "rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}), flush=True)
"""


def load_queries(spec_path: str) -> list:
    """[(image path, cam_from_world prior)] from the JSON list bench_load writes."""
    import numpy as np

    return [(q["image"], np.array(q["prior"])) for q in json.loads(Path(spec_path).read_text())]


def localize_all(loc, queries: list, n: int) -> tuple[list[float], int]:
    """Localize ``n`` queries round-robin: (latency of each in seconds, number localized)."""
    lat, ok = [], 0
    for i in range(n):
        img, prior = queries[i % len(queries)]
        t = time.perf_counter()
        ok += loc.localize(img, prior).success
        lat.append(time.perf_counter() - t)
    return lat, ok


def _summary(k: int, lat: list[float], ok: int, wall: float, rss_mb: float, mode: str) -> dict:
    lat_ms = sorted(1000 * x for x in lat)
    p99 = lat_ms[min(len(lat_ms) - 1, int(round(0.99 * (len(lat_ms) - 1))))]
    return {
        "mode": mode,
        "k": k,
        "queries": len(lat),
        "localized": ok,
        "qps": len(lat) / wall,
        "p50_ms": statistics.median(lat_ms),
        "p99_ms": p99,
        "peak_rss_mb": rss_mb,
        "load": _loadavg(),
    }


def _spawn_ready(script: str, spec: str, n: int, what: str) -> list:
    """``n`` child processes running ``script`` with ``spec``, each past its set-up (it printed "ready")."""
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(ROOT), spec],
            env=ENV,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(n)
    ]
    for p in procs:
        if p.stdout.readline().strip() != "ready":
            raise SystemExit(f"bench_load: {what} failed: {p.stderr.read()[-800:]}")
    return procs


def _go(procs: list) -> None:
    """Start the measured part in every child at once."""
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()


def bench_clients_processes(map_path: Path, qspec: Path, k: int, per_client: int, threads: int | None) -> dict:
    spec = json.dumps({"map": str(map_path), "queries": str(qspec), "n": per_client, "threads": threads})
    procs = _spawn_ready(CLIENT, spec, k, "client")
    t0 = time.perf_counter()
    _go(procs)
    res = [json.loads(p.stdout.readline()) for p in procs]
    wall = time.perf_counter() - t0
    for p in procs:
        p.communicate()
    lat = [x for r in res for x in r["lat"]]
    return _summary(k, lat, sum(r["ok"] for r in res), wall, max(r["rss_kb"] for r in res) / 1024, "processes")


def bench_clients_threads(loc, queries: list, k: int, per_client: int) -> dict:
    out: list = [None] * k
    barrier = threading.Barrier(k + 1)

    def work(i):
        barrier.wait()
        out[i] = localize_all(loc, queries, per_client)

    ts = [threading.Thread(target=work, args=(i,)) for i in range(k)]
    for t in ts:
        t.start()
    barrier.wait()
    t0 = time.perf_counter()
    for t in ts:
        t.join()
    wall = time.perf_counter() - t0
    lat = [x for r in out for x in r[0]]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return _summary(k, lat, sum(r[1] for r in out), wall, rss, "threads")


# -- (c) readers while writers write ---------------------------------------------------------------------
READER = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
from tools.bench_load import load_queries
spec = json.loads(sys.argv[2])
from favormap.localize import Localizer, LocalizeConfig
loc = Localizer(spec["map"], LocalizeConfig(threads=spec["threads"] or "auto"))
queries = load_queries(spec["queries"])
print("ready", flush=True)
sys.stdin.readline()
n = ok = failed = 0
t0 = time.perf_counter()
while time.perf_counter() - t0 < spec["seconds"]:
    img, prior = queries[n % len(queries)]
    try:
        ok += loc.localize(img, prior).success
    except Exception as e:  # counted and reported, never hidden
        failed += 1
        print(f"error: {type(e).__name__}: {e}", file=sys.stderr)
    n += 1
print(json.dumps({"n": n, "ok": ok, "failed": failed, "seconds": time.perf_counter() - t0}), flush=True)
"""


def bench_readers_writers(
    map_path: Path,
    other_map: Path,
    qspec: Path,
    work: Path,
    readers: int,
    seconds: float,
    threads: int | None,
    with_writers: bool,
) -> dict:
    spec = json.dumps({"map": str(map_path), "queries": str(qspec), "seconds": seconds, "threads": threads})
    procs = _spawn_ready(READER, spec, readers, "reader")
    _go(procs)
    writes, bad = 0, []
    t0 = time.perf_counter()
    while with_writers and time.perf_counter() - t0 < seconds:
        out = work / f"written{writes % 2}.h5"
        cmd = (
            _favormap("prune", str(map_path), "-o", str(out), "--max-landmarks", "300", "-q", threads=threads)
            if writes % 2 == 0
            else _favormap("merge", str(map_path), str(other_map), "-o", str(out), "-q", threads=threads)
        )
        r = subprocess.run(cmd, env=ENV, capture_output=True, text=True)
        v = subprocess.run(
            [sys.executable, "-m", "favormap", "validate", str(out)], env=ENV, capture_output=True, text=True
        )
        if r.returncode != 0 or v.returncode != 0:
            bad.append(
                f"{cmd[3]}: rc {r.returncode} {r.stderr.strip()[-200:]} / validate rc {v.returncode} "
                f"{v.stdout.strip()[-200:]}"
            )
        writes += 1
    res = []
    for p in procs:
        out, err = p.communicate()
        r = json.loads(out.strip().splitlines()[-1])
        r["stderr"] = err.strip()[-300:]
        res.append(r)
    n = sum(r["n"] for r in res)
    return {
        "readers": readers,
        "writers": with_writers,
        "writes": writes,
        "bad_writes": bad,
        "queries": n,
        "qps": n / max(r["seconds"] for r in res),
        "localized": sum(r["ok"] for r in res),
        "reader_failures": sum(r["failed"] for r in res),
        "reader_errors": [r["stderr"] for r in res if r["failed"]],
        "load": _loadavg(),
    }


# -- inputs ------------------------------------------------------------------------------------------------
def prepare_inputs(seq_arg: str | None, work: Path) -> Path:
    if seq_arg:
        return Path(seq_arg)
    fern = ROOT.parent / "shared" / "data" / "llff_fern"
    if fern.is_dir():
        return fern
    from favormap.synthetic import write_sequence

    write_sequence(work / "room", n_frames=20, width=504, height=378)
    return work / "room"


def write_queries(seq_path: Path, work: Path, every: int = 4) -> Path:
    """Frames 0, every, 2*every, ... (those ``build --exclude-every`` leaves out of the map), each with
    the pose of the nearest mapping frame as its prior."""
    import numpy as np

    from favormap.geometry import camera_centers
    from favormap.io import read_sequence

    seq = read_sequence(str(seq_path))
    T = np.stack([f.cam_from_world for f in seq.frames])
    c = camera_centers(T)
    mapping = np.array([i for i in range(len(seq)) if i % every])
    qs = []
    for i in range(0, len(seq), every):
        j = mapping[np.argmin(np.linalg.norm(c[mapping] - c[i], axis=1))]
        qs.append({"image": str(seq.frames[i].image_path), "prior": T[j].tolist()})
    p = work / "queries.json"
    p.write_text(json.dumps(qs))
    return p


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequence", help="posed sequence (default ../shared/data/llff_fern, else a synthetic room)")
    ap.add_argument("--sections", default="a,b,c", help="which parts to run (default a,b,c)")
    ap.add_argument("--builds", default="1,2,4", help="concurrent builds of (a) (default 1,2,4)")
    ap.add_argument("--clients", default="1,2,4,8", help="concurrent clients of (b) (default 1,2,4,8)")
    ap.add_argument("--queries", type=int, default=24, help="queries per client in (b) (default 24)")
    ap.add_argument("--readers", type=int, default=2, help="reader processes in (c) (default 2)")
    ap.add_argument("--seconds", type=float, default=20.0, help="duration of (c) (default 20)")
    ap.add_argument("--threads", type=int, help="--threads for every command (default: favormap's rule)")
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args()
    sections = set(args.sections.split(","))

    from favormap.threads import available_cpus, resolve_threads

    tmp = tempfile.TemporaryDirectory(prefix="favormap-load-")
    work = Path(tmp.name)
    seq = prepare_inputs(args.sequence, work)
    print(
        f"machine: {os.cpu_count()} CPUs, {available_cpus()} usable by favormap, threads per process "
        f"{resolve_threads(args.threads)}; load average {_loadavg()}; sequence {seq}",
        flush=True,
    )
    report = {"cpus": os.cpu_count(), "sequence": str(seq), "threads": args.threads}
    if "a" in sections:
        print("(a) concurrent builds vs the same builds in sequence", flush=True)
        report["builds"] = bench_builds(seq, work, [int(x) for x in args.builds.split(",")], args.threads)
    if sections & {"b", "c"}:
        map_path, other = work / "map.h5", work / "other.h5"
        subprocess.run(
            _favormap("build", str(seq), "-o", str(map_path), "--exclude-every", "4", "-q", threads=args.threads),
            env=ENV,
            check=True,
            stdout=subprocess.DEVNULL,
        )
        qspec = write_queries(seq, work)
    if "b" in sections:
        print(
            f"(b) localization clients, {args.queries} queries each (processes, then threads sharing one Localizer)",
            flush=True,
        )
        rows = []
        ks = [int(x) for x in args.clients.split(",")]
        for k in ks:
            rows.append(bench_clients_processes(map_path, qspec, k, args.queries, args.threads))
            _print_client(rows[-1], rows[0])
        from favormap.localize import LocalizeConfig, Localizer

        loc = Localizer(map_path, LocalizeConfig(threads=args.threads or "auto"))
        queries = load_queries(str(qspec))
        localize_all(loc, queries[:1], 1)
        for k in ks:
            rows.append(bench_clients_threads(loc, queries, k, args.queries))
            _print_client(rows[-1], rows[len(ks)])
        loc.close()
        report["clients"] = rows
    if "c" in sections:
        print(
            f"(c) {args.readers} reader processes localizing for {args.seconds:.0f} s, alone and while prune/merge "
            "write new maps in the same folder",
            flush=True,
        )
        subprocess.run(
            _favormap("build", str(seq), "-o", str(other), "--exclude-every", "3", "-q", threads=args.threads),
            env=ENV,
            check=True,
            stdout=subprocess.DEVNULL,
        )
        rows = [
            bench_readers_writers(map_path, other, qspec, work, args.readers, args.seconds, args.threads, w)
            for w in (False, True)
        ]
        for r in rows:
            print(
                f"  {'with writers' if r['writers'] else 'alone       '}: {r['queries']:4d} queries, {r['qps']:5.2f} "
                "q/s, "
                f"{r['reader_failures']} reader failures, {r['writes']} maps written, {len(r['bad_writes'])} invalid"
                f"   load {r['load']}",
                flush=True,
            )
            for msg in r["bad_writes"] + r["reader_errors"]:
                print(f"    {msg}")
        report["readers"] = rows
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    tmp.cleanup()


def _print_client(r: dict, base: dict) -> None:
    print(
        f"  {r['mode']:<9} K={r['k']}: {r['qps']:6.2f} q/s ({r['qps'] / base['qps']:.2f}x K=1)  p50 "
        f"{r['p50_ms']:6.0f} ms  "
        f"p99 {r['p99_ms']:6.0f} ms  peak RSS {r['peak_rss_mb']:5.0f} MB  localized {r['localized']}/{r['queries']}"
        f"   load {r['load']}",
        flush=True,
    )


if __name__ == "__main__":
    main()
