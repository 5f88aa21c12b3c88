import atexit
import os
import shutil
import tempfile

import jax
import numpy as np
import pytest

from jtus import hostmem

# Test processes keep freed memory as every jtus tool does (``cli.run``), before JAX
# starts its threads: the tools' allocator, without fresh pages faulted in each step.
hostmem.keep_freed_memory()

# One persistent compilation cache per test session, shared with the CLI subprocesses
# the tests start: many tests compile the same programs (a train step, the metrics of
# a video) in fresh jit objects, and a cache hit skips XLA's compile (the resume test
# took 51 s without it and 29 s with it, 2 cores). Keys are the programs themselves,
# and the folder is new for each session and removed after it.
# xdist workers (``-n 2``) inherit the controller's folder through JTUS_TEST_JAX_CACHE
if "JTUS_TEST_JAX_CACHE" in os.environ:
    _CACHE = os.environ["JTUS_TEST_JAX_CACHE"]
else:
    _CACHE = os.environ["JTUS_TEST_JAX_CACHE"] = tempfile.mkdtemp(prefix="jtus-test-jax-cache-")
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
for _name, _value in (("jax_compilation_cache_dir", _CACHE),
                      ("jax_persistent_cache_min_compile_time_secs", 0),
                      ("jax_persistent_cache_min_entry_size_bytes", 0)):
    jax.config.update(_name, _value)
    os.environ[_name.upper()] = str(_value)

# Start JAX's backends now, on one CPU device: ``python -m jtus.train``'s main splits
# XLA:CPU into a device per core only before JAX's first computation, and a test that
# calls it in-process must not change the devices of the tests after it. Subprocess
# tests run the CLI as users do; tests/test_sharding.py covers the split.
jax.devices()


@pytest.fixture
def x64():
    """Run a test with 64-bit JAX types enabled."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    """The ``tiny`` preset, generated once per test session (per xdist worker) and
    only read by the tests that take it."""
    from jtus.sim import generate

    path = tmp_path_factory.mktemp("data") / "tiny.h5"
    generate.generate("tiny", path, progress=False)
    return str(path)
