"""A pytest plugin: where each test's time goes in JAX's compile pipeline.

    python -m pytest -q -p tests.compile_profile                 # the whole suite
    python -m pytest -q -p tests.compile_profile --compile-profile-out p.json tests/test_dlctus.py

Each test's call phase is timed beside the seconds JAX reports for it through
``jax.monitoring``: XLA's backend compiles, split at ``SMALL_S`` into small ones (an
eager operation compiled on its own, a tiny jitted helper) and large ones (a model's
step, a training step); lowering to MLIR; tracing; what the persistent compilation
cache saved and what reading it cost. Each process (each xdist worker) writes its rows
to a folder shared through ``JTUS_COMPILE_PROFILE_DIR``; the process that reports
(the xdist controller, or the only process with ``-n 0``) merges them into one JSON
file (``--compile-profile-out``, default ``compile-profile.json``), removes the
folder it made, and prints the totals and the files that spend most on compiling.
Fixture setup and subprocesses (the CLI tests) are not counted. Results of a run:
``docs/results/test-suite/``.
"""

from __future__ import annotations

import collections
import glob
import json
import os
import shutil
import tempfile
import time

import jax.monitoring
import pytest

SMALL_S = 0.15  # backend compiles shorter than this count as small
ENV = "JTUS_COMPILE_PROFILE_DIR"
# jax.monitoring's duration events, by the last part of their name
EVENTS = {"backend_compile_duration": "compile", "jaxpr_to_mlir_module_duration": "lower",
          "jaxpr_trace_duration": "trace", "compile_time_saved_sec": "cache_saved",
          "cache_retrieval_time_sec": "cache_read"}

_current: dict = collections.Counter()
_rows: list = []
_made: list = []  # the folder this process made (and removes once it has merged the rows)


def _on_duration(name, seconds, **_):
    key = EVENTS.get(name.rsplit("/", 1)[-1])
    if key == "compile":
        size = "small" if seconds < SMALL_S else "large"
        _current[f"{size}_compile_s"] += seconds
        _current[f"{size}_compiles"] += 1
    elif key is not None:
        _current[f"{key}_s"] += seconds


def pytest_configure(config):
    """Loaded as a plugin: listen to JAX's compile events; the first process (the xdist
    controller, which starts its workers after this) makes the rows' folder."""
    if ENV not in os.environ:
        os.environ[ENV] = tempfile.mkdtemp(prefix="jtus-compile-profile-")
        _made.append(os.environ[ENV])
    jax.monitoring.register_event_duration_secs_listener(_on_duration)


def pytest_addoption(parser):
    parser.addoption("--compile-profile-out", default="compile-profile.json",
                     help="where tests.compile_profile writes its merged rows (JSON)")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    _current.clear()
    start = time.perf_counter()
    yield
    _rows.append({"test": item.nodeid, "call_s": time.perf_counter() - start,
                  **dict(_current)})


def pytest_sessionfinish(session):
    path = os.path.join(os.environ[ENV], f"rows-{os.getpid()}.json")
    with open(path + ".tmp", "w") as f:
        json.dump(_rows, f)
    os.replace(path + ".tmp", path)


def summarize(rows):
    """Totals over ``rows`` and per test file, the files sorted by compile seconds."""
    keys = sorted({k for r in rows for k in r if k != "test"})
    total = {k: sum(r.get(k, 0) for r in rows) for k in keys}
    by_file = collections.defaultdict(collections.Counter)
    for r in rows:
        f = by_file[r["test"].split("::")[0]]
        f["tests"] += 1
        f.update({k: r.get(k, 0) for k in keys})
    files = sorted(by_file.items(),
                   key=lambda kv: -(kv[1]["small_compile_s"] + kv[1]["large_compile_s"]))
    return total, files


def pytest_terminal_summary(terminalreporter, config):
    if hasattr(config, "workerinput"):  # an xdist worker: the controller reports
        return
    rows = []
    for path in sorted(glob.glob(os.path.join(os.environ[ENV], "rows-*.json"))):
        with open(path) as f:
            rows += json.load(f)
    out = config.getoption("compile_profile_out")
    with open(out + ".tmp", "w") as f:
        json.dump(rows, f, indent=0)
    os.replace(out + ".tmp", out)
    for folder in _made:
        shutil.rmtree(folder, ignore_errors=True)
    total, files = summarize(rows)
    tr = terminalreporter
    tr.section("compile profile (tests.compile_profile)")
    tr.write_line(
        f"{len(rows)} tests, calls {total.get('call_s', 0):.0f} s: small compiles "
        f"{total.get('small_compile_s', 0):.0f} s ({total.get('small_compiles', 0):.0f}), "
        f"large {total.get('large_compile_s', 0):.0f} s ({total.get('large_compiles', 0):.0f}), "
        f"lowering {total.get('lower_s', 0):.0f} s, tracing {total.get('trace_s', 0):.0f} s, "
        f"saved by the cache {total.get('cache_saved_s', 0):.0f} s; rows in {out}")
    for name, f in files[:10]:
        tr.write_line(f"{name}: {f['tests']} tests, {f['call_s']:.0f} s; compiles "
                      f"{f['small_compile_s']:.0f} s small ({f['small_compiles']}), "
                      f"{f['large_compile_s']:.0f} s large, lowering {f['lower_s']:.0f} s")
