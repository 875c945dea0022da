"""The ``favormap`` command line: a thin layer over the Python API.

Each subcommand lives in its own module here with ``register(subparsers)`` that adds its parser and
sets ``func``. Every failure ends in one line on stderr and a non-zero exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from .. import (
    heap,
    threads,  # first: its CPU-load window starts at import (favormap.threads)
)
from ..errors import FavormapError, first_line

# subcommand modules, in --help order
_COMMANDS = [
    "build",
    "info",
    "localize",
    "pose",
    "eval",
    "query",
    "align",
    "merge",
    "extend",
    "prune",
    "export",
    "validate",
    "view",
    "demo",
]


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of usage + error
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def make_parser() -> argparse.ArgumentParser:
    from .. import __version__

    p = _Parser(prog="favormap", description="Visual relocalization with persistent feature-voxel maps (FaVoR).")
    p.add_argument("--version", action="version", version=f"favormap {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in _COMMANDS:
        try:
            mod = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.{name}":
                continue
            raise
        mod.register(sub)
    return p


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (main() may run in-process)."""

    def emit(self, record):
        self.stream = sys.stderr
        super().emit(record)


def _log_to_stderr() -> None:
    """favormap's log lines (e.g. a reader's note about projected rotations) as 'favormap: ...' on stderr."""
    log = logging.getLogger("favormap")
    if not any(isinstance(h, _StderrHandler) for h in log.handlers):
        h = _StderrHandler()
        h.setFormatter(logging.Formatter("favormap: %(message)s"))
        log.addHandler(h)
        log.setLevel(logging.INFO)


def main(argv=None) -> int:
    os.environ.setdefault("RERUN_ANALYTICS", "false")  # the viewer favormap spawns also gets CI=1 (favormap.viz)
    _log_to_stderr()
    parser = make_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        # heavy commands: size the thread pools once, before any work; a command whose API object
        # does it itself at the start of the work (localize: the Localizer) says so, and the load
        # measurement then spans its imports instead of waiting threads.MIN_WINDOW_S for it
        if hasattr(args, "threads") and (args.threads is not None or not getattr(args, "threads_by_api", False)):
            threads.configure_threads(args.threads)
            heap.reuse_freed_blocks()  # large temporaries from reused heap blocks (favormap.heap)
        return int(args.func(args) or 0)
    except FavormapError as e:
        print(f"favormap {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"favormap {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    except Exception as e:  # noqa: BLE001 - last line of defence: one line, no traceback
        if args.debug:
            raise
        print(
            f"favormap {args.command}: internal error: {type(e).__name__}: {first_line(e)} (rerun with --debug for "
            "details)",
            file=sys.stderr,
        )
        return 3


if __name__ == "__main__":
    sys.exit(main())
