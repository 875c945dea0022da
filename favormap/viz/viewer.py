"""Starting and reaching a rerun viewer: the executable, its environment (analytics off unless
opted in), the --rerun-connect URL check."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ..errors import InputError
from . import DEFAULT_PORT


def rerun_executable() -> str | None:
    """The ``rerun`` CLI shipped with rerun-sdk (also reachable as ``python -m rerun``)."""
    import shutil

    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    return shutil.which("rerun")


def analytics_opt_in() -> bool:
    """True when the user explicitly allowed the viewer's anonymous usage analytics."""
    return os.environ.get("RERUN_ANALYTICS", "").strip().lower() in ("1", "true", "yes", "on")


def viewer_environment() -> dict:
    """Environment of a spawned viewer. rerun 0.41 ignores ``RERUN_ANALYTICS``: its viewer turns
    analytics off when ``CI`` is set (or after ``rerun analytics disable``), so the child gets
    ``CI=1`` unless the user opted in with ``RERUN_ANALYTICS=true``. Only the child's environment
    changes, never ours."""
    env = dict(os.environ)
    env["RERUN_APP_ONLY"] = "true"  # what rr.spawn sets too: a viewer app, no first-run prompts
    if not analytics_opt_in():
        env.setdefault("CI", "1")
    return env


def _port_open(port: int, host: str = "127.0.0.1", timeout: float = 0.2) -> bool:
    import socket

    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _check_url(url: str) -> None:
    """Reject malformed --rerun-connect URLs; warn (once, early) when nothing listens there yet."""
    from urllib.parse import urlsplit

    u = urlsplit(url)
    if not u.scheme.startswith("rerun") or not u.hostname:
        raise InputError(f"--rerun-connect expects a URL like rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy, got {url!r}")
    try:
        port = u.port or (443 if u.scheme.endswith("https") else DEFAULT_PORT)
    except ValueError:
        raise InputError(f"--rerun-connect: bad port in {url!r}") from None
    if not _port_open(port, u.hostname, timeout=1.0):
        print(
            f"favormap: warning: no rerun viewer listens at {url} yet (start one with `rerun`); "
            "data logged before it starts may be lost",
            file=sys.stderr,
        )


def spawn_viewer(port: int = DEFAULT_PORT, memory_limit: str = "75%", wait_s: float = 30.0, settle_s: float = 1.0):
    """Start a detached local rerun viewer listening on ``port`` (unless one already listens there)
    and wait until it accepts connections, and ``settle_s`` more in which it must not exit (a viewer
    without a display may open its port before it fails). Returns the viewer's process (None when
    one was listening already). Raises :class:`InputError` when it cannot start (no display, no
    executable)."""
    import subprocess
    import tempfile
    import time

    if _port_open(port):
        return None  # a viewer (or another rerun server) is already listening: reuse it
    exe = rerun_executable()
    if exe is None:
        raise InputError(
            "the rerun viewer executable was not found (it ships with rerun-sdk); "
            "use --rerun-save FILE.rrd and open the file with `rerun FILE.rrd`"
        )
    err = tempfile.TemporaryFile()
    try:
        proc = subprocess.Popen(
            [exe, "--port", str(port), "--memory-limit", memory_limit, "--expect-data-soon", "--hide-welcome-screen"],
            env=viewer_environment(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=err,
            start_new_session=True,
        )
        t_end, listening = time.monotonic() + wait_s, None
        while listening is not None or time.monotonic() < t_end:  # a listening viewer gets its settle_s
            if proc.poll() is not None:
                err.seek(0)
                lines = [ln for ln in err.read().decode(errors="replace").splitlines() if "rror" in ln]
                why = lines[-1].strip()[:300] if lines else f"exit code {proc.returncode}"
                raise InputError(
                    f"the rerun viewer could not start ({why}); use --rerun-save FILE.rrd "
                    "(or --rerun-connect URL of a viewer running elsewhere)"
                )
            if listening is None and _port_open(port):
                listening = time.monotonic()
            if listening is not None and time.monotonic() >= listening + settle_s:
                return proc
            time.sleep(0.1)
        # neither listening nor exited (e.g. a loaded machine without a display): do not stream into nothing
        proc.kill()
        raise InputError(
            f"the rerun viewer could not start (no connection on port {port} within {wait_s:.0f} s); "
            "use --rerun-save FILE.rrd (or --rerun-connect URL of a viewer running elsewhere)"
        )
    finally:
        err.close()
