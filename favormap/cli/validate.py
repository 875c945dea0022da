"""favormap validate map.h5 [--json]"""

from __future__ import annotations

from .common import print_json


def register(sub):
    p = sub.add_parser(
        "validate",
        help="check a map file completely",
        description="Check a map file against the map format schema: structure, dtypes, shapes, attributes, "
        "every dataset's Fletcher-32 checksum (all data is read) and value constraints (finite "
        "numbers, unique ids, index ranges, ...). Lists every problem; exit code 0 when valid.",
    )
    p.add_argument("map", help="map file (HDF5)")
    p.add_argument(
        "--json",
        action="store_true",
        help='print {"valid": bool, "problems": [...], ..., "attributes": {...}, "groups": [...], '
        '"datasets": {...}} as one JSON object: the report and the file\'s layout description, which '
        "the JSON Schema schemas/favormap-map.v1.json validates",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import MapFormatError
    from ..mapfile.validate import format_report, validate

    report = validate(args.map)
    if args.json:
        print_json(report.to_dict())
    else:
        print("\n".join(format_report(report)), flush=True)
    if not report.valid:
        more = len(report.problems) - 1
        raise MapFormatError(
            f"invalid map {args.map}: {report.problems[0]}"
            + (f" (+{more} more problem{'s' if more != 1 else ''})" if more else "")
        )
    return 0
