"""What every command-line tool of jtus does first."""

from __future__ import annotations

import signal
import sys


def _exit_on_term(signum, frame):
    raise SystemExit(128 + signum)


def sigterm_as_exit():
    """Turn SIGTERM into ``SystemExit(143)``, so that a terminated command unwinds like
    an interrupted one: ``atomic_path`` removes its temporary file, and nothing half
    written is left (SIGKILL cannot be caught; its temporary files carry a ``.tmp``
    suffix and are never read)."""
    if sys.platform != "win32":
        signal.signal(signal.SIGTERM, _exit_on_term)
