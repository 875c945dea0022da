#!/usr/bin/env python3
"""Generate the attribute and dataset tables of docs/map-format.md from the map schema.

The tables sit between marker comments in the doc::

    <!-- generated: attributes -->  ...  <!-- end generated -->
    <!-- generated: datasets -->    ...  <!-- end generated -->

and are built from ``schemas/favormap-map.v<N>.json``: each entry's ``description`` and its
``x-favormap`` reading (type or dtype, shape, value constraints, units).

    python tools/gen_map_format_tables.py           # rewrite the tables in docs/map-format.md
    python tools/gen_map_format_tables.py --check   # exit 1 when the doc's tables differ
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "schemas" / "favormap-map.v1.json"
DOC = REPO / "docs" / "map-format.md"
END = "<!-- end generated -->"


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _attribute_constraint(x: dict) -> str:
    parts = []
    if "const" in x:
        c = x["const"]
        parts.append(f"= `{c}`" if len(str(c)) <= 24 else "constant (see meaning)")
    if "min" in x:
        parts.append(f"≥ {x['min']}")
    if x.get("format") == "date-time":
        parts.append("ISO 8601")
    if x.get("nonempty"):
        parts.append("non-empty")
    if x.get("json") == "object":
        parts.append("JSON object")
    return ", ".join(parts)


def _values(x: dict) -> str:
    v = x.get("values", {})
    parts = ["*optional*"] if x.get("optional") else []
    if v.get("finite"):
        parts.append("finite")
    if v.get("not_nan"):
        parts.append("not NaN")
    if v.get("unique"):
        parts.append("unique")
    if v.get("nonzero"):
        parts.append("non-zero")
    if "exclusive_min" in v:
        parts.append(f"> {v['exclusive_min']}")
    if "min" in v:
        parts.append(f"≥ {v['min']}")
    if "max" in v:
        parts.append(f"≤ {v['max']}")
    if v.get("ordered"):
        parts.append("min ≤ max")
    if "unit_norm" in v:
        parts.append(f"unit length (±{v['unit_norm']})")
    if "rigid" in v:
        parts.append(f"rigid (±{v['rigid']})")
    if "range" in v:
        lo, hi = v["range"]
        parts.append(f"in [{lo}, {hi})")
    if "in" in v:
        parts.append(f"in `{v['in']}`")
    if "enum" in v:
        parts.append("one of " + ", ".join(f"`{e}`" for e in v["enum"]))
    if "consistent_with" in v:
        parts.append(f"= observations in `{v['consistent_with']}` (warning)")
    return ", ".join(parts)


def attributes_table(schema: dict) -> str:
    rows = ["| attribute | type | constraint | meaning |", "|---|---|---|---|"]
    for name, e in schema["properties"]["attributes"]["properties"].items():
        x = e["x-favormap"]
        rows.append(f"| `{name}` | {x['type']} | {_cell(_attribute_constraint(x))} | {_cell(e['description'])} |")
    return "\n".join(rows)


def datasets_table(schema: dict) -> str:
    rows = ["| dataset | dtype | shape | values | units | meaning |", "|---|---|---|---|---|---|"]
    for path, e in schema["properties"]["datasets"]["properties"].items():
        x = e["x-favormap"]
        shape = "(" + ", ".join(map(str, x["shape"])) + ")"
        rows.append(
            f"| `{path}` | {x['dtype']} | {shape} | {_cell(_values(x))} | {_cell(x.get('units', ''))} "
            f"| {_cell(e['description'])} |"
        )
    return "\n".join(rows)


def tables(schema: dict) -> dict[str, str]:
    return {"attributes": attributes_table(schema), "datasets": datasets_table(schema)}


def render(doc: str, schema: dict) -> str:
    """``doc`` with every generated block replaced by the table the schema gives."""
    tabs = tables(schema)
    for name, table in tabs.items():
        pat = re.compile(rf"(<!-- generated: {name} -->\n).*?({re.escape(END)})", re.S)
        if not pat.search(doc):
            raise SystemExit(f"error: {DOC.name} has no '<!-- generated: {name} -->' ... '{END}' block")
        doc = pat.sub(lambda m, t=table: m.group(1) + t + "\n" + m.group(2), doc, count=1)
    return doc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 when the doc's tables differ")
    args = ap.parse_args(argv)
    schema = json.loads(SCHEMA.read_text())
    doc = DOC.read_text()
    new = render(doc, schema)
    if args.check:
        if new != doc:
            print(f"error: the tables of {DOC} differ from {SCHEMA.name}: run {Path(__file__).name}", file=sys.stderr)
            return 1
        return 0
    if new != doc:
        DOC.write_text(new)
        print(f"{DOC}: tables regenerated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
