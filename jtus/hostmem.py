"""The host allocator: freed memory kept in the process instead of returned to the
kernel after every step.

XLA:CPU allocates each execution's buffers (temporaries, outputs) with the C library's
``malloc`` and frees them when the execution ends. glibc serves a request above its
mmap threshold (128 KiB, adapting up to 32 MiB) with a fresh ``mmap`` and unmaps it on
``free``, so every training step, frame or rendered tile maps its large buffers anew
and the kernel zeroes each 4 KiB page on its first touch (a minor page fault). On the
2-core AMD EPYC the split ``diverse`` training step took 28,550 such faults (111 MiB) and
64.5 ms of kernel time per step (``python experiments/host_memory.py``,
``docs/performance.md``, "Host memory").

``keep_freed_memory`` tells glibc, for this process only, to serve every request from
its heaps (``M_MMAP_MAX`` 0) and to keep what is freed at a heap's top
(``M_TRIM_THRESHOLD`` 2 GiB): a step reuses the pages of the step before, and the
process holds its high-water mark until it exits. One case stays mapped: a request over
64 MiB from a thread other than the main one, which its arena (a heap of at most 64 MiB)
cannot hold and glibc maps whatever the settings (XLA's 1080p frames). One arena for
every thread (``M_ARENA_MAX`` 1) would hold those too, but the training step's threads
then contend for it and lost the gain (``docs/results/host-memory-one-arena/``). Every
``python -m jtus.<tool>`` calls it first (``cli.run``); library callers may call it
themselves. It changes no value, only
where buffers come from. Where the environment already sets glibc's allocator
(``GLIBC_TUNABLES`` with a ``glibc.malloc.`` tunable, or a ``MALLOC_*_`` variable),
the user's choice stands and nothing is changed.
"""

from __future__ import annotations

import ctypes
import os
import platform

M_TRIM_THRESHOLD = -1   # glibc's mallopt parameters (malloc.h)
M_MMAP_MAX = -4
TRIM_THRESHOLD = 2 ** 31 - 1   # mallopt takes an int: 2 GiB
USER_VARIABLES = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                  "MALLOC_TOP_PAD_", "MALLOC_ARENA_MAX")

_state = []


def user_settings(environ=None):
    """The allocator settings the environment makes (names), empty when none."""
    environ = os.environ if environ is None else environ
    names = [v for v in USER_VARIABLES if v in environ]
    tunables = environ.get("GLIBC_TUNABLES", "")
    names += [t.split("=")[0] for t in tunables.split(":") if t.startswith("glibc.malloc.")]
    return names


def keep_freed_memory():
    """Keep freed memory in this process (see the module's docstring). Returns what
    holds now: ``"kept"``, ``"user"`` (the environment sets the allocator: left as it
    is), or ``"unavailable"`` (not glibc, or ``mallopt`` refused). Idempotent."""
    if _state:
        return _state[0]
    if user_settings():
        state = "user"
    elif platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        state = "unavailable"
    else:
        libc = ctypes.CDLL(None)  # the process's own symbols: glibc's mallopt among them
        ok = all(libc.mallopt(k, v) == 1 for k, v in ((M_MMAP_MAX, 0),
                                                      (M_TRIM_THRESHOLD, TRIM_THRESHOLD)))
        state = "kept" if ok else "unavailable"
    _state.append(state)
    return state


def state():
    """What ``keep_freed_memory`` found (None before it ran in this process)."""
    return _state[0] if _state else None


def describe(s):
    """One phrase for reports, of a ``state()``."""
    return {"kept": "freed memory kept in the process (glibc, jtus.hostmem)",
            "user": "glibc's allocator as the environment sets it",
            "unavailable": "the C library's default allocator",
            None: "the C library's default allocator (on glibc, large freed buffers "
                  "unmapped)"}[s]
