"""From rows to tables: the paired error ratio of two methods on the same queries with its bootstrap interval
(paired_ratio) and its tables per map, per training seed and between two runs (paired_rows / paired_table,
seed_paired_rows / seed_paired_table, compare_rows / compare_table), the --json rows read and written
(read_rows, write_rows), the real-data summary against the baseline (real_rows, real_table; the error the two
share, shared_error, NEES with the ground truth's error, geometric_means over the splits), and the markdown of
every row (markdown, fmt_row, seed_table). Nothing here localizes: it works on the rows alone."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np

from .splits import ANGLE_BINS, CROSS_PRIORS, Split

PAIRED_BOOTSTRAP = 4000  # resamples of the queries for the paired ratio's confidence interval


def paired_ratio(errors: np.ndarray, reference: np.ndarray, seed: int = 0) -> dict | None:
    """How a method's per-query errors compare with a reference's on the same queries (both
    localized): the geometric mean of error / reference error with a 95 % bootstrap interval over the
    queries, and the queries where it is lower / higher. Medians of 5-25 queries move by 10 % between
    training seeds; a paired ratio whose interval excludes 1 is a difference the queries agree on."""
    e, r = np.asarray(errors, np.float64), np.asarray(reference, np.float64)
    ok = np.isfinite(e) & np.isfinite(r) & (e > 0) & (r > 0)
    if ok.sum() < 2:
        return None
    d = np.log(e[ok] / r[ok])
    rng = np.random.default_rng(seed)
    boot = d[rng.integers(0, len(d), (PAIRED_BOOTSTRAP, len(d)))].mean(axis=1)
    lo, hi = np.exp(np.percentile(boot, [2.5, 97.5]))
    return {
        "queries": int(ok.sum()),
        "ratio": float(np.exp(d.mean())),
        "ci95": [float(lo), float(hi)],
        "lower": int((d < 0).sum()),
        "higher": int((d > 0).sum()),
        "log_ratios": [round(float(v), 6) for v in d],  # per query, for intervals over several splits
    }


def _errors(row: dict, names: list[str]) -> np.ndarray:
    """A row's translation error per query ``names`` (inf where it failed or is missing)."""
    by = {q["name"]: (q["t_err"] if q["success"] else np.inf) for q in row.get("per_query", [])}
    return np.array([by.get(n, np.inf) for n in names], np.float64)


def _baseline_ref_prior(prior: str) -> str:
    """The prior mode of the favormap rows a baseline row is paired with: the noise priors for the
    baseline's own prior-free localization, the same mode for its stream."""
    return "noise" if prior == "none" else prior


def paired_rows(rows: list[dict], reference: str = "rendered") -> list[dict]:
    """Every method against ``reference`` on the same map, split and prior mode (and the baseline
    against the first map's reference under the noise priors), overall and per angle bin."""
    import re

    out = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if r.get("per_query"):
            groups.setdefault((r["split"], r.get("map_variant")), []).append(r)
    for (split, variant), rs in groups.items():
        for prior in dict.fromkeys(r["prior"] for r in rs):
            ref = [
                r
                for r in rs
                if r["prior"] == prior and re.sub(rf"^{re.escape(variant or '')} ?", "", r["method"]) == reference
            ]
            if variant is None:  # the baseline: against the first map's reference (noise priors; a stream: a stream)
                ref = [r for r in rows if r["split"] == split and r.get("map_variant") is not None]
                ref = [r for r in ref if r["prior"] == _baseline_ref_prior(prior) and r["method"] == reference][:1]
            if not ref:
                continue
            names = [q["name"] for q in ref[0]["per_query"]]
            angle = np.array([q.get("angle_deg", np.nan) for q in ref[0]["per_query"]], np.float64)
            e_ref = _errors(ref[0], names)
            for r in rs:
                if r["prior"] != prior or r is ref[0]:
                    continue
                e = _errors(r, names)
                row = {"split": split, "prior": r["prior"], "method": r["method"], "reference": ref[0]["method"]}
                row["all"] = paired_ratio(e, e_ref)
                row["failed"] = int(np.isinf(e).sum()), int(np.isinf(e_ref).sum())
                if np.isfinite(angle).any():
                    row["bins"] = {
                        f"{lo}-{hi}": paired_ratio(e[(angle >= lo) & (angle < hi)], e_ref[(angle >= lo) & (angle < hi)])
                        for lo, hi in ANGLE_BINS
                    }
                out.append(row)
    return out


def _map_and_seed(r: dict, seed_of: dict | None = None) -> tuple[str | None, int, str]:
    """A row's map variant without its seed suffix (NAME-sK / sK -> NAME / ""), the seed, and the
    method without the map's prefix. ``seed_of``: {map name: training seed} of the run's builds; None:
    the seed read from the name as the benchmark writes it ("sK" / "NAME-sK" for seed K > 0)."""
    import re

    name = r.get("map_variant")
    if name is None:
        return None, 0, r["method"]
    method = re.sub(rf"^{re.escape(name)} ?", "", r["method"]) if name else r["method"]
    if seed_of is not None:
        base = re.sub(r"(^|-)s\d+$", "", name) if seed_of.get(name) else name
        return base, seed_of.get(name, 0), method
    m = re.fullmatch(r"(?:(.*)-)?s(\d+)", name)
    return (m.group(1) or "", int(m.group(2)), method) if m else (name, 0, method)


def seed_paired_rows(rows: list[dict], build_cfgs, reference: str = "rendered") -> list[dict]:
    """Every method of every map variant (and the baseline) against ``reference`` on the default map
    of the same training seed, query by query, with each query's log ratio averaged over the seeds
    before the bootstrap: one decision per (split, prior, map variant, method) over all seeds."""
    seed_of = {name: cfg.voxel.seed for name, cfg in build_cfgs}
    refs: dict[tuple, dict] = {}
    groups: dict[tuple, list[tuple[int, dict]]] = {}
    for r in rows:
        if not r.get("per_query"):
            continue
        base, seed, method = _map_and_seed(r, seed_of)
        if base == "" and method == reference:
            refs[(r["split"], r["prior"], seed)] = r
        groups.setdefault((r["split"], r["prior"], base, method), []).append((seed, r))
    out = []
    for (split, prior, base, method), members in groups.items():
        if base == "" and method == reference:
            continue
        logs, names, angle, seeds = [], None, None, set()
        for seed, r in members:
            if base is None:  # the baseline has no seed: against the default map of every seed
                against = [(k[2], v) for k, v in refs.items() if k[0] == split and k[1] == _baseline_ref_prior(prior)]
            else:
                against = [(seed, refs[split, prior, seed])] if (split, prior, seed) in refs else []
            for ref_seed, ref in against:
                if names is None:
                    names = [q["name"] for q in ref["per_query"]]
                    angle = np.array([q.get("angle_deg", np.nan) for q in ref["per_query"]], np.float64)
                with np.errstate(divide="ignore", invalid="ignore"):
                    logs.append(np.log(_errors(r, names) / _errors(ref, names)))
                seeds.add(ref_seed)
        if not logs:
            continue
        out.append(_seed_mean_row(split, prior, base, method, sorted(seeds), logs, angle))
    return out


def _seed_mean_row(split, prior, base, method, seeds, logs, angle) -> dict:
    """A paired row from per-seed log error ratios (seeds x queries): each query's mean over the
    seeds (nan / inf where a seed failed or tied at 0: left out), overall and per angle bin."""
    d = np.mean(logs, axis=0)
    row = {"split": split, "prior": prior, "map": base if base is not None else "(baseline)", "method": method}
    row["seeds"] = seeds
    row["all"] = paired_ratio(np.exp(d), np.ones_like(d))
    if np.isfinite(angle).any():
        row["bins"] = {
            f"{lo}-{hi}": paired_ratio(
                np.exp(d[(angle >= lo) & (angle < hi)]), np.ones(((angle >= lo) & (angle < hi)).sum())
            )
            for lo, hi in ANGLE_BINS
        }
    return row


def seed_paired_table(rows: list[dict], build_cfgs, reference: str = "rendered") -> str:
    """Markdown of :func:`seed_paired_rows`."""
    return _ratio_table(
        f"Paired with `{reference}` of the default map and the same training seed (per query, the log error ratio "
        "averaged over the seeds; geometric mean [95 % bootstrap interval over the queries], queries lower / higher):",
        ["split", "prior", "map", "method", "seeds"],
        [
            ([p["split"], p["prior"], p["map"] or "(default)", p["method"], ",".join(map(str, p["seeds"]))], p)
            for p in seed_paired_rows(rows, build_cfgs, reference)
        ],
    )


def paired_table(rows: list[dict], reference: str = "rendered") -> str:
    """Markdown of :func:`paired_rows`: ratio [95 % interval] and queries lower/higher."""
    return _ratio_table(
        f"Paired with `{reference}` of the same map (error / reference error, geometric mean over the queries both "
        "localized [95 % bootstrap interval], queries lower / higher; < 1: better than the reference):",
        ["split", "prior", "method", "failed (method / ref.)"],
        [
            ([p["split"], p["prior"], p["method"], f"{p['failed'][0]} / {p['failed'][1]}"], p)
            for p in paired_rows(rows, reference)
        ],
    )


def read_rows(path) -> list[dict]:
    """A run's --json rows, from a plain or a gzip-compressed (``.gz``) file."""
    path = Path(path)
    raw = path.read_bytes()
    return json.loads(gzip.decompress(raw) if path.suffix == ".gz" else raw)


def write_rows(path, rows: list[dict]) -> None:
    """Write a run's rows as JSON; gzip-compressed where the name ends in ``.gz`` (docs/benchmarks keeps
    its runs so: they are ~14x smaller, and the working tree a GPU check carries is limited to 64 MiB)."""
    path = Path(path)
    text = json.dumps(rows, indent=1, default=float).encode()
    path.write_bytes(gzip.compress(text, mtime=0) if path.suffix == ".gz" else text)


def compare_rows(ref_rows: list[dict], new_rows: list[dict]) -> list[dict]:
    """Two runs of the benchmark (e.g. two versions of the code, the same splits and seeds): every
    (split, prior, map, method) in both, the new run's error over the reference run's query by query
    and seed by seed, each query's log ratio averaged over the seeds both runs have."""
    ref = {}
    for r in ref_rows:
        if r.get("per_query"):
            base, seed, method = _map_and_seed(r)
            ref[(r["split"], r["prior"], base, method, seed)] = r
    groups: dict[tuple, list[tuple[int, dict]]] = {}
    for r in new_rows:
        if r.get("per_query"):
            base, seed, method = _map_and_seed(r)
            if (r["split"], r["prior"], base, method, seed) in ref:
                groups.setdefault((r["split"], r["prior"], base, method), []).append((seed, r))
    out = []
    for (split, prior, base, method), members in groups.items():
        logs, names, angle = [], None, None
        for seed, r in sorted(members, key=lambda m: m[0]):
            old = ref[(split, prior, base, method, seed)]
            if names is None:
                names = [q["name"] for q in old["per_query"]]
                angle = np.array([q.get("angle_deg", np.nan) for q in old["per_query"]], np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                logs.append(np.log(_errors(r, names) / _errors(old, names)))
        out.append(_seed_mean_row(split, prior, base, method, sorted(m[0] for m in members), logs, angle))
    return out


def pool_rows(runs: list[list[dict]]) -> list[dict]:
    """Several runs of the benchmark as one: every (split, prior, map, method, seed) in all of them, each query
    localized where the majority of the runs localized it, with the median of those runs' errors (and NEES).
    Each suite run builds the structure baseline's SfM map anew, and COLMAP's threads make each build a little
    different: the baseline's errors move by up to ~10 % per split between runs while favormap's stay put, so a
    ratio to one run's baseline carries that run's luck."""
    keyed = []
    for rows in runs:
        by = {}
        for r in rows:
            if r.get("per_query"):
                base, seed, method = _map_and_seed(r)
                by[(r["split"], r["prior"], base, method, seed)] = r
        keyed.append(by)
    out = []
    for key, first in keyed[0].items():
        members = [k[key] for k in keyed if key in k]
        if len(members) < len(keyed):
            continue
        row = dict(first, per_query=[])
        by_name = [{x["name"]: x for x in m["per_query"]} for m in members]
        for q in first["per_query"]:
            got = [b.get(q["name"]) for b in by_name]
            ok = [x for x in got if x is not None and x["success"]]
            pooled = dict(q, success=2 * len(ok) > len(got))
            if ok:
                pooled["t_err"] = float(np.median([x["t_err"] for x in ok]))
                pooled["r_err_deg"] = float(np.median([x["r_err_deg"] for x in ok]))
                nees = [x["nees"] for x in ok if x.get("nees") is not None]
                pooled["nees"] = float(np.median(nees)) if nees else None
            row["per_query"].append(pooled)
        out.append(row)
    return out


def compare_table(ref_rows: list[dict], new_rows: list[dict]) -> str:
    """Markdown of :func:`compare_rows`."""
    return _ratio_table(
        "New run / reference run, the same method on the same queries (per query, the log error ratio averaged "
        "over the seeds; geometric mean [95 % bootstrap interval over the queries], queries lower / higher; "
        "< 1: the new run is better):",
        ["split", "prior", "map", "method", "seeds"],
        [
            ([p["split"], p["prior"], p["map"] or "(default)", p["method"], ",".join(map(str, p["seeds"]))], p)
            for p in compare_rows(ref_rows, new_rows)
        ],
    )


def _ratio_cell(p: dict | None) -> str:
    if p is None:
        return "-"
    return f"{p['ratio']:.2f} [{p['ci95'][0]:.2f}, {p['ci95'][1]:.2f}] {p['lower']}/{p['higher']}"


def _ratio_table(intro: str, lead: list[str], entries: list[tuple[list[str], dict]]) -> str:
    """A markdown table of paired ratios: the ``lead`` columns, then all queries and each angle bin."""
    if not entries:
        return ""
    bins = [f"{lo}-{hi}" for lo, hi in ANGLE_BINS]
    out = [
        intro,
        "",
        "| " + " | ".join(lead + ["all queries"] + bins) + " |",
        "|---" * (len(lead) + 1 + len(bins)) + "|",
    ]
    for cells, p in entries:
        b = p.get("bins") or {}
        out.append(
            "| "
            + " | ".join(cells + [_ratio_cell(p["all"])] + [_ratio_cell(b.get(k)) if b else "" for k in bins])
            + " |"
        )
    return "\n".join(out)


def _query_arrays(row: dict, names: list[str]):
    by = {q["name"]: q for q in row["per_query"]}
    qs = [by.get(n) for n in names]
    succ = np.array([bool(q and q["success"]) for q in qs])
    t = np.array([q["t_err"] if q else np.inf for q in qs], np.float64)
    r = np.array([q["r_err_deg"] if q else np.inf for q in qs], np.float64)
    return succ, t, r


def _method_stats(split: Split, row: dict, names: list[str]) -> dict:
    """One method's figures on a real split, from its per-query rows: medians over the localized
    queries in the set's units and as % of the path extent, recall, localized share, false successes
    (localized with an error above the split's false_success: 5 % of the path extent or 5 deg unless it
    says otherwise) and the median NEES of the reported covariance."""
    succ, t, r = _query_arrays(row, names)
    ext = split.path_extent
    fs_t, fs_r = split.false_success or (0.05 * ext, 5.0)
    med_t = float(np.median(t[succ])) if succ.any() else None
    by = {q["name"]: q for q in row["per_query"]}
    nees = [by[n]["nees"] for n in names if n in by and by[n].get("nees") is not None]
    return {
        "median_t": med_t,
        "median_t_pct_path": None if med_t is None else 100 * med_t / ext,
        "median_r_deg": float(np.median(r[succ])) if succ.any() else None,
        "recall": {f"{tt:.4g}/{rr:g}deg": float(np.mean(succ & (t <= tt) & (r <= rr))) for tt, rr in split.recall},
        "localized": int(succ.sum()),
        "queries": len(names),
        "false_successes": int((succ & ((t > fs_t) | (r > fs_r))).sum()),
        "median_nees": float(np.median(nees)) if nees else None,
    }


def real_rows(rows: list[dict], splits: list[Split], reference: str = "rendered") -> list[dict]:
    """Per real split and favormap map (the default and each --build-variant): favormap's ``reference``
    method under the noise priors and the baseline side by side, with the paired ratio of their
    translation errors (favormap / baseline over the queries both localized, 95 % bootstrap interval)."""
    out = []
    for sp in splits:
        if sp.path_extent is None:
            continue
        base = [r for r in rows if r["split"] == sp.name and r["method"] == "pycolmap-SIFT" and r["prior"] == "none"]
        favs = [
            r
            for r in rows
            if r["split"] == sp.name
            and (r["prior"] in CROSS_PRIORS if sp.cross else r["prior"] == "noise")
            and r.get("map_variant") is not None
            and r["method"] == " ".join(w for w in (r["map_variant"], reference) if w)
        ]
        names = [f.name for f in sp.queries.frames]
        b_stats = _method_stats(sp, base[0], names) if base else None
        for f in favs:
            entry = {
                "split": sp.name,
                "prior": f["prior"],
                "cross": sp.cross,
                "map": f["map_variant"] or "(default)",
                "mapping_frames": len(sp.mapping),
                "units": sp.units,
                "path_extent": sp.path_extent,
                "favormap": _method_stats(sp, f, names),
                "landmarks": f.get("landmarks"),
                "build_s_per_frame": None if f.get("build_s") is None else f["build_s"] / len(sp.mapping),
                "map_bytes_per_landmark": f.get("map_bytes_per_landmark"),
                "build_stats": f.get("build_stats"),
            }
            if base:
                succ_f, t_f, _ = _query_arrays(f, names)
                succ_b, t_b, _ = _query_arrays(base[0], names)
                entry["baseline"] = b_stats
                entry["baseline_points"] = base[0].get("landmarks")
                entry["ratio"] = paired_ratio(np.where(succ_f, t_f, np.inf), np.where(succ_b, t_b, np.inf))
                entry["baseline_only"] = int((succ_b & ~succ_f).sum())  # localized by the baseline, not by favormap
                entry["shared"] = shared_error(f, base[0], names)
                if sp.cross and entry["shared"]:
                    entry["favormap"]["median_nees_gt"] = nees_with_ground_truth_error(
                        f, names, entry["shared"]["gt_sigma"]
                    )
            out.append(entry)
    return out


def shared_error(row: dict, base: dict, names: list[str]) -> dict | None:
    """How much of two methods' errors they share, over the queries both localized: the median distance
    between their camera centres, and the median cosine between their centres' error vectors. Errors
    that point the same way and estimates that lie closer to each other than to the truth are the
    ground truth's (or the given mapping poses') own error, which neither method can remove."""
    a = {q["name"]: q for q in row.get("per_query", []) if q["success"] and "t_vec" in q}
    b = {q["name"]: q for q in base.get("per_query", []) if q["success"] and "t_vec" in q}
    both = [n for n in names if n in a and n in b]
    if len(both) < 2:
        return None
    ea = np.array([a[n]["t_vec"] for n in both])
    eb = np.array([b[n]["t_vec"] for n in both])
    norm = np.linalg.norm(ea, axis=1) * np.linalg.norm(eb, axis=1)
    cos = np.sum(ea * eb, 1) / np.maximum(norm, 1e-300)
    return {
        "queries": len(both),
        "apart": float(np.median(np.linalg.norm(ea - eb, axis=1))),
        "cosine": float(np.median(cos)),
        # the ground truth's own error per axis: two methods' errors e_a = g + a and e_b = g + b share the ground
        # truth's g, and with a, b independent of g and of each other E[e_a . e_b] = E|g|^2 = 3 sigma^2
        "gt_sigma": float(np.sqrt(max(np.mean(np.sum(ea * eb, 1)), 0.0) / 3)),
    }


def nees_with_ground_truth_error(row: dict, names: list[str], gt_sigma: float) -> float | None:
    """Median NEES of a method's localized queries against a ground truth with ``gt_sigma`` of its own error
    per axis: the camera-centre error under the reported covariance plus gt_sigma^2 I (chi-square with 3
    degrees of freedom, median 2.37, when both are right)."""
    by = {q["name"]: q for q in row.get("per_query", [])}
    out = []
    for n in names:
        q = by.get(n)
        if q and q["success"] and "center_cov" in q:
            e = np.asarray(q["t_vec"], np.float64)
            C = np.asarray(q["center_cov"], np.float64) + gt_sigma**2 * np.eye(3)
            try:
                out.append(float(e @ np.linalg.solve(C, e)))
            except np.linalg.LinAlgError:
                continue
    return float(np.median(out)) if out else None


def geometric_means(entries: list[dict], seed: int = 0) -> dict[str, tuple[float, list[float] | None]]:
    """Per favormap map: the geometric mean over the same-recording splits of the paired ratios to the
    baseline, and its 95 % bootstrap interval (each split's queries resampled within the split; None where a
    ratio lacks its per-query log ratios). Cross-recording splits are reported on their own."""
    by: dict[str, list[dict]] = {}
    for e in entries:
        if e.get("ratio") and not e.get("cross"):
            by.setdefault(e["map"], []).append(e["ratio"])
    rng = np.random.default_rng(seed)
    out = {}
    for k, ratios in by.items():
        value = float(np.exp(np.mean([np.log(r["ratio"]) for r in ratios])))
        ci = None
        if all(r.get("log_ratios") for r in ratios):
            boot = np.mean(
                [
                    np.asarray(r["log_ratios"])[
                        rng.integers(0, len(r["log_ratios"]), (PAIRED_BOOTSTRAP, len(r["log_ratios"])))
                    ].mean(1)
                    for r in ratios
                ],
                axis=0,
            )
            ci = [float(v) for v in np.exp(np.percentile(boot, [2.5, 97.5]))]
        out[k] = (value, ci)
    return out


def _split_label(entry: dict) -> str:
    """A real-table entry's split, with its prior mode where a cross-recording split runs several."""
    return entry["split"] + (f" ({entry['prior']} prior)" if entry.get("cross") else "")


def real_table(entries: list[dict]) -> str:
    """Markdown of :func:`real_rows`, and one line per favormap map: the geometric mean of the ratios."""
    if not entries:
        return ""
    rec_keys = []
    for e in entries:
        for k in range(len(e["favormap"]["recall"])):
            rec_keys.append(k) if k not in rec_keys else None

    def st(s, e):
        if s is None:
            return ["-"] * 5
        rec = " / ".join(f"{100 * v:.0f}" for v in s["recall"].values())
        return [
            f"{_f(s['median_t'], '.4f')} ({_f(s['median_t_pct_path'], '.2f')} %)",
            _f(s["median_r_deg"], ".3f"),
            rec,
            f"{s['localized']}/{s['queries']}",
            str(s["false_successes"]),
        ]

    out = [
        "| split | map | frames map / queries | path extent | favormap median t (% path) | R (deg) | recall % | "
        "localized | FS | NEES | baseline median t (% path) | R (deg) | recall % | localized | FS | favormap / "
        "baseline [95 % CI] | baseline-only | landmarks / points | build s/frame | map B/landmark |",
        "|---" * 20 + "|",
    ]
    for e in entries:
        r = e.get("ratio")
        ratio = "-" if not r else f"{r['ratio']:.2f} [{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}]"
        bps = e.get("build_s_per_frame")
        bpl = e.get("map_bytes_per_landmark")
        out.append(
            "| "
            + " | ".join(
                [
                    _split_label(e),
                    e["map"],
                    f"{e['mapping_frames']} / {e['favormap']['queries']}",
                    f"{e['path_extent']:.3f} {e['units']}",
                    *st(e["favormap"], e),
                    _f(e["favormap"].get("median_nees"), ".1f"),
                    *st(e.get("baseline"), e),
                    ratio,
                    str(e.get("baseline_only", "-")),
                    f"{e.get('landmarks') or '-'} / {e.get('baseline_points') or '-'}",
                    _f(bps, ".2f"),
                    _f(bpl, ".0f"),
                ]
            )
            + " |"
        )
    out.append("")
    out.append(
        "Recall thresholds: 0.5 % of the path extent / 2 deg, 2 % / 5 deg (and for 7-Scenes 5 cm / 5 deg, "
        "2 cm / 2 deg); FS: false successes (localized, error > 5 % of the path extent or 5 deg). Another "
        "recording (tum-desk-xyz): recall at 2 cm / 2 deg, 5 cm / 5 deg, 10 cm / 10 deg, a false success beyond "
        "10 cm or 10 deg (its ground truth is off by ~1-2 cm itself), favormap from each prior mode, the baseline "
        "without a prior. NEES: median over the localized queries of the camera-centre error under the reported "
        "covariance (2.37 when that covariance is right)."
    )
    for k, (v, ci) in geometric_means(entries).items():
        n = sum(1 for e in entries if e["map"] == k and e.get("ratio") and not e.get("cross"))
        interval = "" if ci is None else f" [{ci[0]:.3f}, {ci[1]:.3f}]"
        out.append(f"geometric mean of favormap / baseline over {n} splits, map {k}: {v:.3f}{interval}")
    shared = [e for e in entries if e.get("shared")]
    if shared:
        out += [
            "",
            "Error shared with the baseline (queries both localize): the median distance between the two "
            "estimates, against each method's median error, the median cosine between their error vectors, the "
            "ground truth's own error per axis that the two share (sqrt of the mean dot product of their error "
            "vectors over 3) and, on another recording, favormap's median NEES with that error added to its "
            "covariance",
            "",
            "| split | map | estimates apart | favormap median t | baseline median t | cosine of the errors | "
            "ground truth's error per axis | favormap NEES with it |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for e in shared:
            sh = e["shared"]
            out.append(
                f"| {_split_label(e)} | {e['map']} | {sh['apart']:.4f} | {_f(e['favormap']['median_t'], '.4f')} | "
                f"{_f(e['baseline']['median_t'], '.4f')} | {sh['cosine']:.2f} | {sh['gt_sigma']:.4f} | "
                f"{_f(e['favormap'].get('median_nees_gt'), '.1f')} |"
            )
    return "\n".join(out)


def _f(v, spec):
    return "-" if v is None else format(v, spec)


def fmt_row(s: dict) -> str:
    iters = "/".join(_f(it["median_translation"], ".4f") for it in s["per_iteration"])
    return (
        f"med {_f(s['median_translation'], '.4f')} ({_f(s['median_translation_pct_extent'], '.2f')} %) "
        f"p90 {_f(s['p90_translation'], '.4f')}  R {_f(s['median_rotation_deg'], '.3f')}  "
        f"loc {100 * s['success_rate']:.0f} %  FS {s['false_successes']}  inl {s['mean_inliers']:.0f}  "
        f"iters {iters}  {s['mean_time_s'] * 1000:.0f} ms  prec {_f(s['match_precision'], '.2f')}  "
        f"rep {_f(s['keypoint_repeatability'], '.2f')}  floor {_f(s.get('median_noise_floor'), '.4f')}  "
        f"NEES {_f(s.get('median_nees'), '.1f')}"
    )


def seed_table(rows: list[dict], build_cfgs) -> str:
    """Markdown table of each favormap method's median translation across the training seeds of
    its map (rows of maps named NAME-sK / sK are grouped with NAME's)."""
    import re

    seed_of = {name: cfg.voxel.seed for name, cfg in build_cfgs}
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        if "map_variant" not in r:  # the baseline
            continue
        name = r["map_variant"]
        base = re.sub(r"(^|-)s\d+$", "", name) if seed_of.get(name) else name
        method = r["method"] if name == base else re.sub(rf"(^| ){re.escape(name)}( |$)", rf"\1{base}\2", r["method"])
        key = (r["split"], r["prior"], " ".join(method.split()))
        groups.setdefault(key, []).append(dict(r, seed=seed_of.get(name, 0)))
    out = [
        "| split | prior | method | seeds | median t per seed (units) | range | mean | localized | false succ. |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (split, prior, method), rs in groups.items():
        rs.sort(key=lambda r: r["seed"])
        med = [r["median_translation"] for r in rs]
        ok = [m for m in med if m is not None]
        fmt = [f"{m:.4f}" if m is not None else "-" for m in med]
        rng = f"{min(ok):.4f}-{max(ok):.4f}" if ok else "-"
        mean = f"{np.mean(ok):.4f}" if ok else "-"
        loc = f"{sum(r['localized'] for r in rs)}/{sum(r['queries'] for r in rs)}"
        fs = sum(r["false_successes"] for r in rs)
        seeds = ",".join(str(r["seed"]) for r in rs)
        out.append(f"| {split} | {prior} | {method} | {seeds} | {' / '.join(fmt)} | {rng} | {mean} | {loc} | {fs} |")
    return "\n".join(out)


def markdown(rows: list[dict]) -> str:
    out = [
        "| split | prior | method | landmarks | median t (units) | % extent | p90 t | median R (deg) | localized | "
        "false succ. | inliers | median t per iter | s/query | match prec. @GT | kp repeat. @GT | noise floor | "
        "residual px | median NEES |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in rows:
        iters = " / ".join(_f(it["median_translation"], ".4f") for it in s["per_iteration"])
        out.append(
            f"| {s['split']} | {s['prior']} | {s['method']} | {s.get('landmarks') or '-'} | "
            f"{_f(s['median_translation'], '.4f')} | {_f(s['median_translation_pct_extent'], '.2f')} | "
            f"{_f(s['p90_translation'], '.4f')} | {_f(s['median_rotation_deg'], '.3f')} | "
            f"{s['localized']}/{s['queries']} | {s['false_successes']} | {s['mean_inliers']:.0f} | {iters} | "
            f"{s['mean_time_s']:.2f} | {_f(s['match_precision'], '.2f')} | {_f(s['keypoint_repeatability'], '.2f')} | "
            f"{_f(s.get('median_noise_floor'), '.4f')} | {_f(s.get('median_residual_px'), '.2f')} | "
            f"{_f(s.get('median_nees'), '.1f')} |"
        )
    bins = [s for s in rows if s.get("bins")]
    if bins:
        out += [
            "",
            "Per angle to the nearest mapping view (deg): localized / queries, median translation (units), match "
            "precision @GT",
            "",
            "| split | prior | method | " + " | ".join(f"{lo}-{hi}" for lo, hi in ANGLE_BINS) + " |",
            "|---|---|---|" + "---|" * len(ANGLE_BINS),
        ]
        for s in bins:
            cells = []
            for lo, hi in ANGLE_BINS:
                b = s["bins"].get(f"{lo}-{hi}")
                cells.append(
                    "-"
                    if b is None
                    else f"{b['localized']}/{b['queries']}, {_f(b['median_translation'], '.4f')}, "
                    f"{_f(b['precision'], '.2f')}"
                )
            out.append(f"| {s['split']} | {s['prior']} | {s['method']} | " + " | ".join(cells) + " |")
    return "\n".join(out)
