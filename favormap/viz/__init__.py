"""Rerun recordings of what favormap does: build, localize, eval, merge, prune and a map viewer.

Every long-running command takes ``--rerun`` (spawn a viewer), ``--rerun-save FILE.rrd`` (write a
recording) and ``--rerun-connect URL`` (stream to a running viewer). Without any of them
:func:`recording_from_args` returns ``None``: nothing is logged and rerun is not even imported.

This module is imported by every CLI command, so it stays light; the recorder itself lives in
:mod:`favormap.viz.recording`. Entity paths are documented in ``docs/rerun.md``.
"""

from __future__ import annotations

import argparse

DEFAULT_PORT = 9876
DEFAULT_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"

__all__ = ["add_rerun_args", "recording_from_args", "rerun_requested", "DEFAULT_URL"]


def add_rerun_args(parser: argparse.ArgumentParser, spawn_by_default: bool = False) -> None:
    """Add ``--rerun``, ``--rerun-save FILE`` and ``--rerun-connect URL`` to a subcommand parser."""
    g = parser.add_argument_group("rerun visualisation (see docs/rerun.md)")
    g.add_argument(
        "--rerun",
        action="store_true",
        help="spawn a rerun viewer and stream to it" + (" (the default)" if spawn_by_default else ""),
    )
    g.add_argument("--rerun-save", metavar="FILE.rrd", help="write a rerun recording to this file")
    g.add_argument("--rerun-connect", metavar="URL", help=f"stream to a running rerun viewer, e.g. {DEFAULT_URL}")


def rerun_requested(args) -> bool:
    return bool(
        getattr(args, "rerun", False) or getattr(args, "rerun_save", None) or getattr(args, "rerun_connect", None)
    )


def recording_from_args(args, app_id: str, map_=None, spawn: bool = False):
    """A :class:`favormap.viz.recording.Recording` for the rerun flags of ``args``, or ``None`` when
    no flag was given. ``map_`` (a Map or MapData) is logged as context (landmarks, camera path).
    ``spawn=True`` spawns a viewer even without ``--rerun`` (used by ``favormap view``)."""
    if not (spawn or rerun_requested(args)):
        return None
    try:
        from .recording import Recording
    except ImportError as e:
        if (e.name or "").split(".")[0] not in ("rerun", "rerun_bindings"):
            raise
        from ..errors import InputError

        raise InputError("the rerun flags need rerun-sdk 0.41 (pip install 'rerun-sdk>=0.41,<0.42')") from None

    kind = getattr(args, "command", None) or app_id.split()[-1]
    methods = None
    if kind == "eval":
        methods = ["rendered"] + ([] if getattr(args, "no_baseline", False) else ["mean"])
    elif kind == "localize":
        methods = [getattr(args, "descriptors", None) or "rendered"]
    return Recording(
        app_id,
        kind=kind,
        spawn=bool(spawn or getattr(args, "rerun", False)),
        save=getattr(args, "rerun_save", None),
        connect=getattr(args, "rerun_connect", None),
        map_=map_,
        methods=methods,
    )
