"""favormap eval map.h5 QUERY_SEQ [--prior-mode MODE] [--noise 0.3,10] [--json]"""

from __future__ import annotations

from ..viz import add_rerun_args, recording_from_args
from .common import StageBars, print_json
from .localize import add_localize_options, config_from_args, open_map


def register(sub):
    p = sub.add_parser(
        "eval",
        help="evaluate localization on a posed query sequence",
        description="Localize every frame of a posed sequence from a prior and report errors per "
        "iteration, success rate, false successes and recall, next to the mean-descriptor "
        "baseline on the same map. Query frames are numbered from 0 in the sequence's "
        "order; --every N takes frames 0, N, 2N, ... (those 'build --exclude-every N' leaves out).",
    )
    p.add_argument("map")
    p.add_argument("queries", help="posed query sequence (any supported format)")
    p.add_argument("--format", help="force the query sequence format")
    p.add_argument(
        "--prior-mode",
        choices=["noise", "nearest", "constant", "none", "sequential", "stream"],
        default="noise",
        help="noise: ground truth moved by --noise; nearest: nearest mapping frame; constant: first mapping "
        "frame; none: no prior; sequential: the queries as a stream, the first without a prior, each next one "
        "from the poses estimated before it (constant velocity); stream: sequential, and the landmarks refined from "
        "the queries localized so far, as localize --sequential (default noise)",
    )
    p.add_argument("--noise", default="0.3,10", help="prior perturbation 'T_UNITS,DEG' (default 0.3,10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--every", type=int, default=1, help="use every k-th query frame: 0, k, 2k, ... (default 1)")
    p.add_argument("--split", help="only frames of this split (e.g. test), when the format has splits")
    p.add_argument("--no-baseline", action="store_true", help="skip the mean-descriptor baseline")
    p.add_argument(
        "--diagnostics",
        action="store_true",
        help="also measure match precision and keypoint repeatability at the ground-truth pose, and each pose's "
        "noise floor (how far its inliers' own noise moves it)",
    )
    add_localize_options(p)
    p.add_argument("--json", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true")
    add_rerun_args(p)
    p.set_defaults(func=run)


def parse_noise(s: str) -> tuple[float, float]:
    from ..errors import InputError

    try:
        t, r = (float(x) for x in s.split(","))
    except ValueError:
        raise InputError(f"--noise must be 'T_UNITS,DEG', got {s!r}") from None
    if t < 0 or r < 0:
        raise InputError("--noise values must be >= 0")
    return t, r


def run(args) -> int:
    import dataclasses

    from ..errors import InputError
    from ..io import read_sequence
    from ..localize import Localizer
    from ..localize.evaluate import EvalConfig, evaluate, format_table

    methods = ("rendered",) if args.no_baseline else ("rendered", "mean")
    cfg = EvalConfig(prior_mode=args.prior_mode, noise=parse_noise(args.noise), seed=args.seed, methods=methods)
    lcfg = config_from_args(args)
    queries = read_sequence(args.queries, args.format)
    idx = list(range(len(queries)))
    if args.split:
        split = queries.extra.get("split")
        if not split:
            raise InputError(f"the query sequence has no splits (format {queries.format})")
        idx = [i for i in idx if split[i] == args.split]
    if args.every < 1:
        raise InputError("--every must be >= 1")
    idx = idx[:: args.every]
    if not idx:
        raise InputError("no query frames selected")
    queries = queries.subset(idx)
    m = open_map(args)
    locs = {name: Localizer(m, dataclasses.replace(lcfg, descriptors=name)) for name in methods}
    bars = StageBars(args.quiet or args.json)
    rec = recording_from_args(args, "favormap eval", m)
    try:
        reports = evaluate(
            locs,
            queries,
            cfg,
            progress=bars,
            diagnostics=args.diagnostics,
            on_query=(
                lambda method, i, o: rec.log_eval_query(
                    method, i, o, queries.frames[i], queries.cameras[queries.frames[i].camera_id]
                )
            )
            if rec is not None
            else None,
        )
    finally:
        bars.close()
        m.close()
        if rec is not None:
            rec.close()
    if args.json:
        print_json(
            {
                "map": args.map,
                "queries": args.queries,
                "prior_mode": cfg.prior_mode,
                "noise": list(cfg.noise),
                "units": {"translation": "scene units", "rotation": "degrees", "time": "seconds"},
                "methods": {r.method: r.summary for r in reports},
            }
        )
    else:
        print(format_table(reports))
    return 0
