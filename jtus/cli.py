"""What every command-line tool of jtus does first, and how it ends."""

from __future__ import annotations

import os
import signal
import sys
import warnings

from jtus import hostmem
from jtus.files import UnknownKeyWarning


class Terminated(SystemExit):
    """A SIGTERM, raised where the program was so that it unwinds like an interrupt."""


_TERMINATED = []


def _exit_on_term(signum, frame):
    _TERMINATED.append(signum)
    raise Terminated(128 + signum)


def sigterm_as_exit():
    """Turn SIGTERM into ``Terminated`` (``SystemExit(143)``), so that a terminated
    command unwinds like an interrupted one: ``atomic_path`` removes its temporary file,
    and nothing half written is left (SIGKILL cannot be caught; its temporary files
    carry a ``.tmp`` suffix and are never read)."""
    if sys.platform != "win32":
        signal.signal(signal.SIGTERM, _exit_on_term)


def _show_warning(message, category, filename, lineno, file=None, line=None,
                  _default=warnings.showwarning):
    if issubclass(category, UnknownKeyWarning):
        print(f"warning: {message}", file=sys.stderr if file is None else file)
    else:
        _default(message, category, filename, lineno, file, line)


def run(main):
    """``sys.exit(main())`` for a tool's ``__main__``, printing jtus's warnings about
    input files as one ``warning:`` line each (Python's format adds a source line).
    After a SIGTERM has unwound (its files cleaned up), the process ends at once with
    status 143. A normal interpreter shutdown there can crash (SIGSEGV, measured on
    about half of the SIGTERMs during ``data generate``) while XLA's threads still run
    the interrupted computation. First it keeps freed memory in the process
    (``hostmem.keep_freed_memory``: no page faults for buffers each step maps anew)."""
    hostmem.keep_freed_memory()
    shown, warnings.showwarning = warnings.showwarning, _show_warning
    try:
        code = main()
    except Terminated as e:
        code = e.code
    finally:
        warnings.showwarning = shown
    if _TERMINATED:
        # also when the exception was swallowed on its way (raised inside a ``__del__``
        # or a C callback, Python only prints it): the work then finished, its files
        # are complete, and the exit status still says it was terminated
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(128 + _TERMINATED[0])
    sys.exit(code)
