"""The host allocator setting: freed memory kept in the process, so that a buffer freed
and allocated again maps no fresh pages; the environment's own allocator settings stand;
every command-line tool applies it."""

import os
import platform
import subprocess
import sys

import pytest

from jtus import hostmem

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# The main thread and then a worker thread each malloc, fill and free a buffer six times,
# as XLA:CPU does with an execution's buffers: 96 MiB, then 48 MiB (a thread's arena
# holds at most 64 MiB); glibc maps either on its own by default (above 32 MiB). The
# minor page faults of the last five rounds of each. (NumPy would ask for huge pages.)
REUSE = """
import ctypes, resource, sys, threading
from jtus import hostmem
if sys.argv[1] == "keep":
    assert hostmem.keep_freed_memory() == "kept"
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
faults = []
def work(size):
    for i in range(6):
        if i == 1:
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)
        a = libc.malloc(size)
        ctypes.memset(a, 1, size)
        libc.free(a)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt)
work(96 * 2 ** 20)
t = threading.Thread(target=work, args=(48 * 2 ** 20,))
t.start()
t.join()
print(faults[1] - faults[0], faults[3] - faults[2])
"""


def _clean_env(**extra):
    env = {k: v for k, v in os.environ.items()
           if k not in hostmem.USER_VARIABLES and k != "GLIBC_TUNABLES"}
    return dict(env, PYTHONPATH=ROOT, **extra)


def _python(code, *args, **env):
    return subprocess.run([sys.executable, "-c", code, *args], env=_clean_env(**env),
                          check=True, capture_output=True, text=True).stdout.strip()


def _faults(mode, **env):
    return [int(n) for n in _python(REUSE, mode, **env).split()]


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_kept_memory_maps_no_fresh_pages_for_a_buffer_allocated_again():
    for mib, default, kept in zip((96, 48), _faults("default"), _faults("keep")):
        pages = 5 * mib * 2 ** 20 // 4096     # what five fresh buffers fault in
        assert default > 0.9 * pages, (mib, default, pages)
        assert kept < 0.01 * pages, (mib, kept, pages)


def test_the_environments_allocator_settings_are_named():
    assert hostmem.user_settings({}) == []
    assert hostmem.user_settings({"PATH": "/bin", "GLIBC_TUNABLES": "glibc.cpu.x86_shstk=0"}) \
        == []
    assert hostmem.user_settings({"MALLOC_ARENA_MAX": "4"}) == ["MALLOC_ARENA_MAX"]
    assert hostmem.user_settings(
        {"GLIBC_TUNABLES": "glibc.cpu.x86_shstk=0:glibc.malloc.trim_threshold=131072"}) \
        == ["glibc.malloc.trim_threshold"]


@pytest.mark.skipif(not GLIBC, reason="the setting is glibc's")
def test_the_environments_allocator_settings_stand():
    code = "from jtus import hostmem; print(hostmem.keep_freed_memory())"
    assert _python(code, GLIBC_TUNABLES="glibc.malloc.trim_threshold=131072") == "user"
    assert _python(code, MALLOC_MMAP_MAX_="65536") == "user"
    assert _python(code) == "kept"


def test_every_command_line_tool_applies_it():
    code = "from jtus import cli, hostmem; cli.run(lambda: print(hostmem.state()) or 0)"
    assert _python(code) == ("kept" if GLIBC else "unavailable")
