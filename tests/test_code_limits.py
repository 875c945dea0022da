"""Size limits that keep the code readable: no module of favormap over MAX_MODULE_LINES lines, no
function over MAX_FUNCTION_LINES lines (from its ``def`` line to its last line) unless the first line
of its body is a comment ``# long: <reason>`` saying why it stays whole (an option table, say)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "favormap"
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80
LONG_MARK = "# long:"


def _functions(tree: ast.AST, prefix: str = ""):
    """(qualified name, node) of every function and method, nested ones included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield prefix + node.name, node
            yield from _functions(node, f"{prefix}{node.name}.")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, f"{prefix}{node.name}.")
        else:
            yield from _functions(node, prefix)


def _marked_long(lines: list[str], node: ast.FunctionDef) -> bool:
    """Whether the function's body opens with a ``# long: <reason>`` comment."""
    first = node.body[0]
    start = min([first.lineno] + [d.lineno for d in getattr(first, "decorator_list", [])])
    i = start - 2  # the line above the first statement (0-based)
    block = []
    while i >= node.lineno and lines[i].strip().startswith("#"):
        block.append(lines[i].strip())
        i -= 1
    if not block:
        return False
    top = block[-1]
    return top.startswith(LONG_MARK) and len(top[len(LONG_MARK) :].strip()) > 0


def offenders() -> dict[str, str]:
    """What breaks the limits, by "path" or "path:function", with the measure."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).as_posix()
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        if len(lines) > MAX_MODULE_LINES:
            out[rel] = f"{len(lines)} lines (limit {MAX_MODULE_LINES})"
        for name, node in _functions(ast.parse(text, rel)):
            length = node.end_lineno - node.lineno + 1
            if length > MAX_FUNCTION_LINES and not _marked_long(lines, node):
                out[f"{rel}:{name}"] = (
                    f"{length} lines (limit {MAX_FUNCTION_LINES}; or open it with '{LONG_MARK} <reason>')"
                )
    return out


def test_modules_and_functions_within_the_limits():
    found = offenders()
    assert not found, "split these along their stages:\n" + "\n".join(f"  {k}: {v}" for k, v in found.items())


def test_the_long_mark_is_read_from_the_first_body_line():
    src = (
        "def marked(a,\n"
        "           b):\n"
        "    # long: one table\n"
        '    """doc"""\n'
        "    return a\n"
        "\n"
        "def reasonless():\n"
        "    # long:\n"
        "    return 1\n"
        "\n"
        "def later():\n"
        "    x = 1\n"
        "    # long: too late\n"
        "    return x\n"
    )
    lines = src.splitlines()
    fns = dict(_functions(ast.parse(src)))
    assert _marked_long(lines, fns["marked"])
    assert not _marked_long(lines, fns["reasonless"])
    assert not _marked_long(lines, fns["later"])
