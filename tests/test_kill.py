"""SIGKILL at a random moment: afterwards every output file is the previous
complete version or the new complete version, never a mix, and a killed training run
resumes to the parameters of an uninterrupted one.

The kill moments are drawn from a seeded generator; CI takes one per tool, and
``JTUS_KILL_POINTS=N python -m pytest tests/test_kill.py`` tries N (docs/reliability.md).
"""

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from jtus import checkpoint, loading, recipe, train
from jtus.config import PRESETS
from jtus.data import dataset
from jtus.sim import generate

KILLS = int(os.environ.get("JTUS_KILL_POINTS", "1"))
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def _start(args):
    return subprocess.Popen([sys.executable, "-m"] + args, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def _signal(proc, sig, ready, delay, timeout=300):
    """Send ``sig`` ``delay`` seconds after ``ready()`` first holds, unless ``proc`` has
    exited by then; returns whether it was still running when signalled."""
    deadline = time.time() + timeout
    while not ready() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    end = time.time() + delay
    while time.time() < end and proc.poll() is None:
        time.sleep(0.01)
    alive = proc.poll() is None
    if alive:
        proc.send_signal(sig)
    proc.wait(120)
    return alive


def _interrupt_generate(folder, out, sig, delay, tries=4):
    """Run ``generate --preset diverse-tiny --out out`` (in ``folder``) and send ``sig``
    ``delay`` seconds after its temporary file appears. diverse-tiny renders for 3-9 s
    from then (2-core CPU, varying from session to session), so a run that finished
    first is run again with a quarter of the delay. Returns the signalled process and
    the digest of ``out`` before its run (None if there was none)."""
    for _ in range(tries):
        before = _digest(out) if os.path.exists(out) else None
        proc = _start(["jtus.data", "generate", "--preset", "diverse-tiny", "--out", str(out),
                       "--quiet"])
        if _signal(proc, sig, lambda: any(f.endswith(".tmp") for f in os.listdir(folder)),
                   delay):
            return proc, before
        delay /= 4
    pytest.fail(f"generate finished before each of {tries} signals")


def _temp_files(folder):
    return [f for f in os.listdir(folder) if f.endswith(".tmp") or f.startswith(".")]


@pytest.mark.parametrize("k", range(KILLS))
def test_generate_killed_leaves_the_previous_dataset(tmp_path, k, tiny_data):
    out = tmp_path / "d.h5"
    shutil.copyfile(tiny_data, out)  # a previous dataset, whole
    delay = np.random.default_rng([1, k]).uniform(0.0, 6.0)
    proc, before = _interrupt_generate(tmp_path, out, signal.SIGKILL, delay)
    # the previous version or the new one, whole: a kill that lands after the new file's
    # rename, while the process exits, leaves the new version (generation is
    # deterministic, so the new version is the bytes of an uninterrupted run, rendered
    # here only when the file is not the previous version)
    if _digest(out) != before:
        complete = tmp_path / "complete" / "d.h5"
        generate.generate("diverse-tiny", complete, progress=False)
        assert _digest(out) == _digest(complete)
    with dataset.Dataset(out) as ds:
        assert ds.videos("test")


# the SIGTERM variant is in the long run (python -m pytest -m long); the default run
# checks SIGTERM's handler (temporary files removed, exit 143) on generate and upsample
@pytest.mark.parametrize("sig", [signal.SIGKILL, pytest.param(signal.SIGTERM,
                                                              marks=pytest.mark.long)],
                         ids=["KILL", "TERM"])
@pytest.mark.parametrize("k", range(KILLS))
def test_train_killed_resumes_to_the_uninterrupted_parameters(tmp_path, k, sig, tiny_data):
    config = dataclasses.replace(PRESETS["tiny"], dataset=tiny_data, epochs=8)
    full, _ = train.train_and_evaluate(config, tmp_path / "full", progress=False)
    work = tmp_path / "cut"
        # the first epoch compiles; the 7 after it take about 0.3 s each here
    delay = np.random.default_rng([2, k, int(sig)]).uniform(0.0, 0.6)
    # one device, as the resume below in this process: a run resumed on another device
    # count sums its gradients in another order (float rounding, not bit-equal)
    proc = _start(["jtus.train", "--preset", "tiny", "--dataset", tiny_data, "--epochs", "8",
                   "--workdir", str(work), "--quiet", "--no-eval", "--host-devices", "1"])
    ckpt = work / "checkpoint.msgpack"
    assert _signal(proc, sig, ckpt.exists, delay), "training finished before the signal"
    if sig == signal.SIGTERM:
        assert not _temp_files(work)
        # 143; or 0 when the signal came as the finished run was exiting
        assert proc.returncode == 128 + signal.SIGTERM or (
            proc.returncode == 0 and len(checkpoint.restore_train_state(
                str(work), train.create_train_state(full, recipe.optimizer_for(config)))[2]) == 8)
    if ckpt.exists():  # every checkpoint on disk is whole: it restores
        checkpoint.restore_train_state(
            str(work), train.create_train_state(full, recipe.optimizer_for(config)))
    resumed, hist = train.train_and_evaluate(config, work, resume=True, progress=False)
    assert [h["epoch"] for h in hist] == list(range(1, 9))
    for a, b in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))




@pytest.mark.parametrize("k", range(KILLS))
def test_generate_terminated_removes_its_temporary_file(tmp_path, k, tiny_data):
    out = tmp_path / "d.h5"
    shutil.copyfile(tiny_data, out)  # a previous dataset, whole
    before = _digest(out)
    delay = np.random.default_rng([3, k]).uniform(0.0, 6.0)
    proc, _ = _interrupt_generate(tmp_path, tmp_path / "new.h5", signal.SIGTERM, delay)
    assert proc.returncode == 128 + signal.SIGTERM
    assert _digest(out) == before and not _temp_files(tmp_path)
    # absent, or whole when the signal's exception was swallowed (jtus.cli.run)
    if (tmp_path / "new.h5").exists():
        with dataset.Dataset(tmp_path / "new.h5") as ds:
            assert ds.videos("test")


def _exr_frames(folder, n, size, seed):
    from jtus.data import exr
    folder.mkdir()
    rng = np.random.default_rng(seed)
    for t in range(n):
        ch = {c: rng.uniform(0, 1, size) for c in "RGB"}
        if size[0] < 64:  # the LR inputs
            ch.update({"Z": rng.uniform(0.1, 0.9, size), "motion.X": np.zeros(size),
                       "motion.Y": np.zeros(size)})
        exr.write_exr(folder / f"f{t:03d}.exr", ch)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["KILL", "TERM"])
@pytest.mark.parametrize("k", range(KILLS))
def test_import_exr_interrupted_leaves_the_previous_dataset(tmp_path, k, sig):
    """Re-import (``--force``) over an existing dataset, interrupted at a random moment
    of the run: the file is the previous import or the new one, whole."""
    for name, seed in (("lr", 0), ("hr", 1), ("lr2", 2), ("hr2", 3)):
        _exr_frames(tmp_path / name, 24, (32, 32) if name.startswith("lr") else (128, 128),
                    seed)
    out, new = tmp_path / "d.h5", tmp_path / "new.h5"
    args = ["jtus.data", "import-exr", "--factor", "4"]
    t0 = time.time()
    assert subprocess.run([sys.executable, "-m"] + args + [
        "--input", str(tmp_path / "lr2"), "--target", str(tmp_path / "hr2"), "--out", str(new)],
        cwd=ROOT, capture_output=True).returncode == 0
    duration = time.time() - t0
    assert subprocess.run([sys.executable, "-m"] + args + [
        "--input", str(tmp_path / "lr"), "--target", str(tmp_path / "hr"), "--out", str(out)],
        cwd=ROOT, capture_output=True).returncode == 0
    before, after = _digest(out), _digest(new)
    assert before != after
    delay = np.random.default_rng([4, k, int(sig)]).uniform(0.0, duration)
    proc = _start(args + ["--input", str(tmp_path / "lr2"), "--target", str(tmp_path / "hr2"),
                          "--out", str(out), "--force"])
    _signal(proc, sig, lambda: True, delay)
    assert _digest(out) in (before, after)
    if sig == signal.SIGTERM:
        assert not _temp_files(tmp_path)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["KILL", "TERM"])
@pytest.mark.parametrize("k", range(KILLS))
def test_upsample_interrupted_leaves_only_whole_frames(tmp_path, k, sig, tiny_data):
    """``upsample --force`` over an earlier run's frames, interrupted: every frame file
    is the earlier version or the new one, whole (frames are written one by one,
    atomically)."""
    out = tmp_path / "frames"
    common = ["jtus.upsample", "--input", tiny_data, "--factor", "4", "--format", "exr",
              "--out", str(out)]
    first = subprocess.run([sys.executable, "-m"] + common + ["--model", "jau"], cwd=ROOT,
                           capture_output=True)
    assert first.returncode == 0, first.stderr
    old = {f: _digest(out / f) for f in os.listdir(out)}
    ref = tmp_path / "ref"
    t0 = time.time()
    assert subprocess.run([sys.executable, "-m"] + common[:-1] + [str(ref), "--model", "tus"],
                          cwd=ROOT, capture_output=True).returncode == 0
    duration = time.time() - t0
    new = {f: _digest(ref / f) for f in os.listdir(ref)}
    # TUS's first frame is the jitter-aligned input, as JAU's: every later one differs
    assert set(new) == set(old) and sum(new[f] != old[f] for f in new) == len(new) - 1
    delay = np.random.default_rng([5, k, int(sig)]).uniform(0.0, duration)
    proc = _start(common + ["--model", "tus", "--force"])
    _signal(proc, sig, lambda: True, delay)
    got = {f: _digest(out / f) for f in os.listdir(out) if not f.startswith(".")
           and not f.endswith(".tmp")}
    assert set(got) == set(old)
    assert all(got[f] in (old[f], new[f]) for f in got)
    if sig == signal.SIGTERM:
        assert not _temp_files(out)


@pytest.mark.parametrize("k", range(max(2, KILLS)))
def test_train_overwrite_killed_leaves_the_old_run_whole(tmp_path, k, tiny_data):
    """``train --overwrite`` over a finished run, SIGKILLed at a seeded moment: until
    the new run's first checkpoint the old run's files are all there, byte for byte;
    after it, the new checkpoint is whole (it restores)."""
    work = tmp_path / "run"
    base = ["jtus.train", "--preset", "tiny", "--dataset", tiny_data, "--workdir", str(work),
            "--quiet", "--no-eval", "--epochs", "1"]
    assert subprocess.run([sys.executable, "-m"] + base, cwd=ROOT,
                          capture_output=True).returncode == 0
    old = {f: _digest(work / f) for f in os.listdir(work)}
    delay = np.random.default_rng([7, k]).uniform(0.0, 15.0)
    proc = _start(base + ["--overwrite", "--seed", "7", "--epochs", "2"])
    _signal(proc, signal.SIGKILL, lambda: True, delay)
    now = {f: _digest(work / f) for f in os.listdir(work) if not f.endswith(".tmp")}
    if now["checkpoint.msgpack"] == old["checkpoint.msgpack"]:
        assert now == old
    else:
        config = dataclasses.replace(PRESETS["tiny"], dataset=tiny_data)
        params = loading.init_params(config)
        checkpoint.restore_train_state(
            str(work), train.create_train_state(params, recipe.optimizer_for(config)))


@pytest.mark.parametrize("k", range(KILLS))
def test_evaluate_killed_leaves_whole_results(tmp_path, k, tiny_data):
    """``evaluate --out`` over an earlier run's results, SIGKILLed at a seeded moment:
    each result file (the table, the JSON summary, the plots) is the earlier version or
    a whole new one (each is written beside its path and renamed)."""
    from PIL import Image

    out = tmp_path / "eval"
    base = ["jtus.evaluate", "--dataset", tiny_data, "--factor", "4", "--quiet", "--json",
            "--out", str(out), "--models"]
    t0 = time.time()
    assert subprocess.run([sys.executable, "-m"] + base + ["jau"], cwd=ROOT,
                          capture_output=True).returncode == 0
    duration = time.time() - t0
    old = {f: _digest(out / f) for f in os.listdir(out)}
    assert set(old) == {"results.md", "results.json", "per_frame_x4.png", "crops_x4.png"}
    delay = np.random.default_rng([9, k]).uniform(0.0, duration)
    _signal(_start(base + ["tus"]), signal.SIGKILL, lambda: True, delay)
    for f in old:
        path = out / f
        if _digest(path) == old[f]:
            continue
        if f == "results.json":
            assert list(json.load(open(path))["4"]) == ["tus"]
        elif f == "results.md":
            text = path.read_text()
            assert "| 4x | tus |" in text and text.endswith("\n")
        else:
            with Image.open(path) as im:
                im.verify()
