"""Timers and a description of the machine, for every benchmark and profile.

Every timer calls its function once to warm it up (the first call of a jitted function
compiles and is not counted), then reports the median of ``repeats`` blocking calls.
On a shared, noisy machine only ratios taken in the same minutes mean much:
``timeit_round_robin`` times several functions in turn for that.
"""

from __future__ import annotations

import os
import platform
import time

import jax
import numpy as np


def hardware():
    """``{"cpu", "cores", "jax", "backend", "device"}`` of this process's machine."""
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    name = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = jax.devices()[0]
    return {"cpu": name, "cores": os.cpu_count(), "jax": jax.__version__,
            "backend": dev.platform, "device": getattr(dev, "device_kind", str(dev))}


def hardware_line(hw=None):
    """One line naming the machine, for the foot of a results file."""
    hw = hw or hardware()
    return f"{hw['cpu']}, {hw['cores']} cores, JAX {hw['jax']} on {hw['backend']}"


def timeit(fn, repeats=5):
    """Median seconds of ``fn()`` (which must block) after one warm-up call."""
    return timeit_round_robin({"fn": fn}, repeats)["fn"]


def timeit_round_robin(fns, repeats=5):
    """``{name: median seconds}`` of each blocking ``fns[name]()``, timed in turn (a, b,
    c, a, b, c, ...) after one warm-up call each, so that all see the same machine: on
    a shared, noisy machine their ratios are then steadier than separate medians'."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def timeit_pair(fa, fb, repeats=5):
    """Median seconds of ``fa()`` and of ``fb()``, timed alternately
    (``timeit_round_robin`` of the two)."""
    t = timeit_round_robin({"a": fa, "b": fb}, repeats)
    return t["a"], t["b"]
