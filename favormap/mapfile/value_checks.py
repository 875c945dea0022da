"""The checks of the schema's ``values`` constraints on one dataset's array, by kind of constraint
(:func:`favormap.mapfile.schema.check_values` reads the constraints and runs them). Each returns its
problems, one line each, in the order the constraints are listed here."""

from __future__ import annotations

import numpy as np


def dims_bound(b, dims):
    """A bound of a ``range``: a number, or the name of a dimension in ``dims``."""
    return dims.get(b) if isinstance(b, str) else b


def count_values(mask) -> str:
    """'n value(s)': how many of ``mask`` are set."""
    n = int(np.count_nonzero(mask))
    return f"{n} value{'s' if n != 1 else ''}"


def nonfinite_problems(path: str, a: np.ndarray, spec: dict) -> list[str]:
    """``finite`` and ``not_nan`` of a float array, in the array's own dtype (as in float64: a cast keeps
    it; a map's 20 MB of voxel descriptors need no float64 copy for it)."""
    problems = []
    if spec.get("finite"):
        bad = ~np.isfinite(a)
        if bad.any():
            problems.append(f"{path!r}: {count_values(bad)} not finite (NaN or inf)")
    if spec.get("not_nan"):
        bad = np.isnan(a)
        if bad.any():
            problems.append(f"{path!r}: {count_values(bad)} NaN")
    return problems


def bound_problems(path: str, a: np.ndarray, cmp: np.ndarray, spec: dict, dims: dict) -> list[str]:
    """``min``, ``max``, ``exclusive_min`` (on ``cmp``: the values with NaN as 0), ``nonzero`` and the index
    ``range`` of a numeric array."""
    problems = []
    if "min" in spec and (cmp < spec["min"]).any():
        problems.append(f"{path!r}: {count_values(cmp < spec['min'])} below {spec['min']}")
    if "max" in spec and (cmp > spec["max"]).any():
        problems.append(f"{path!r}: {count_values(cmp > spec['max'])} above {spec['max']}")
    if "exclusive_min" in spec and (cmp <= spec["exclusive_min"]).any():
        problems.append(f"{path!r}: {count_values(cmp <= spec['exclusive_min'])} not above {spec['exclusive_min']}")
    if spec.get("nonzero") and (a == 0).any():
        problems.append(f"{path!r}: {count_values(a == 0)} zero")
    if "range" in spec:
        lo, hi = (dims_bound(b, dims) for b in spec["range"])
        if lo is not None and hi is not None:
            bad = (a < lo) | (a >= hi)
            if bad.any():
                problems.append(f"{path!r}: {count_values(bad)} outside [{lo}, {hi}) (index out of range)")
    return problems


def row_problems(path: str, a: np.ndarray, af: np.ndarray, cmp: np.ndarray, spec: dict) -> list[str]:
    """The constraints on rows of a numeric array: ``unit_norm``, ``ordered`` and ``rigid`` (4 x 4 poses)."""
    problems = []
    if "unit_norm" in spec and a.ndim >= 1:
        n = np.linalg.norm(af, axis=-1)
        bad = np.isfinite(n) & (np.abs(n - 1) > spec["unit_norm"])
        if bad.any():
            problems.append(f"{path!r}: {count_values(bad)} not unit length")
    if spec.get("ordered") and a.ndim >= 1 and a.shape[-1] > 1:
        bad = (np.diff(cmp, axis=-1) < 0).any(-1)
        if bad.any():
            problems.append(f"{path!r}: {count_values(bad)} rows not in increasing order")
    if "rigid" in spec and a.ndim == 3 and a.shape[1:] == (4, 4):
        tol = spec["rigid"]
        T = np.where(np.isfinite(af), af, 0.0)
        Rm = T[:, :3, :3]
        ortho = np.abs(np.einsum("nji,njk->nik", Rm, Rm) - np.eye(3)).max((1, 2)) > tol
        det = np.linalg.det(Rm) < 0
        last = np.abs(T[:, 3] - [0, 0, 0, 1]).max(1) > tol
        bad = ortho | det | last
        if bad.any():
            problems.append(
                f"{path!r}: {count_values(bad)} not a rigid transform (rotation + translation, last row 0 0 0 1)"
            )
    return problems


def membership_problems(path: str, a: np.ndarray, spec: dict, arrays: dict) -> list[str]:
    """``unique``, ``enum`` and ``in`` (the values of another dataset of ``arrays``)."""
    problems = []
    if spec.get("unique"):
        u, c = np.unique(a, return_counts=True)
        if (c > 1).any():
            problems.append(f"{path!r}: {int((c > 1).sum())} duplicated value(s), e.g. {u[c > 1][0]!r}")
    if "enum" in spec:
        vals = [v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v) for v in a.ravel().tolist()]
        bad = sorted({v for v in vals if v not in spec["enum"]})
        if bad:
            problems.append(
                f"{path!r}: unknown value(s) {', '.join(map(repr, bad[:3]))} (allowed: {', '.join(spec['enum'])})"
            )
    if "in" in spec and spec["in"] in arrays and arrays[spec["in"]] is not None:
        bad = ~np.isin(a, arrays[spec["in"]])
        if bad.any():
            problems.append(f"{path!r}: {count_values(bad)} not in {spec['in']!r}, e.g. {a[bad].ravel()[0]!r}")
    return problems
