"""SIGKILL at a random moment (issue 15): afterwards every output file is the previous
complete version or the new complete version, never a mix, and a killed training run
resumes to the parameters of an uninterrupted one.

The kill moments are drawn from a seeded generator; CI takes one per tool, and
``JTUS_KILL_POINTS=N python -m pytest tests/test_kill.py`` tries N (docs/reliability.md).
"""

import dataclasses
import hashlib
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from jtus import checkpoint, recipe, train
from jtus.config import PRESETS
from jtus.data import dataset

KILLS = int(os.environ.get("JTUS_KILL_POINTS", "1"))
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def _start(args):
    return subprocess.Popen([sys.executable, "-m"] + args, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _kill_when(proc, ready, delay, timeout=300):
    """SIGKILL ``proc`` ``delay`` seconds after ``ready()`` first holds (or when it has
    exited by itself); returns whether it was still running when killed."""
    deadline = time.time() + timeout
    while not ready() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(delay)
    alive = proc.poll() is None
    if alive:
        proc.send_signal(signal.SIGKILL)
    proc.wait(60)
    return alive


@pytest.mark.parametrize("k", range(KILLS))
def test_generate_killed_leaves_the_previous_dataset(tmp_path, k):
    out = tmp_path / "d.h5"
    dataset.generate("tiny", out, progress=False)
    before = _digest(out)
    # diverse-tiny renders for about 9 s once its temporary file exists (2-core CPU)
    delay = np.random.default_rng([1, k]).uniform(0.0, 6.0)
    proc = _start(["jtus.data", "generate", "--preset", "diverse-tiny", "--out", str(out),
                   "--quiet"])
    assert _kill_when(proc, lambda: any(f.endswith(".tmp") for f in os.listdir(tmp_path)),
                      delay), "generate finished before the kill"
    # the previous version, whole (a run that finished first wrote the same bytes)
    assert _digest(out) == before
    with dataset.Dataset(out) as ds:
        assert ds.videos("test")


@pytest.mark.parametrize("k", range(KILLS))
def test_train_killed_resumes_to_the_uninterrupted_parameters(tmp_path, k):
    data = tmp_path / "tiny.h5"
    dataset.generate("tiny", data, progress=False)
    config = dataclasses.replace(PRESETS["tiny"], dataset=str(data), epochs=8)
    full, _ = train.train_and_evaluate(config, tmp_path / "full", progress=False)
    work = tmp_path / "cut"
    # after its first checkpoint the run has 7 epochs left, about 0.7 s each here
    delay = np.random.default_rng([2, k]).uniform(0.0, 1.5)
    proc = _start(["jtus.train", "--preset", "tiny", "--dataset", str(data), "--epochs", "8",
                   "--workdir", str(work), "--quiet", "--no-eval"])
    ckpt = work / "checkpoint.msgpack"
    assert _kill_when(proc, ckpt.exists, delay), "training finished before the kill"
    if ckpt.exists():  # every checkpoint on disk is whole: it restores
        checkpoint.restore_train_state(
            str(work), train.create_train_state(full, recipe.optimizer_for(config)))
    resumed, hist = train.train_and_evaluate(config, work, resume=True, progress=False)
    assert [h["epoch"] for h in hist] == list(range(1, 9))
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

