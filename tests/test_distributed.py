"""Multi-process data parallelism (``jax.distributed``, gloo between CPU processes):
two local processes, each with half of the global batch, make the update one process
makes on the whole batch; ``python -m jtus.train --distributed`` trains with them."""

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

STEP = textwrap.dedent("""
    import sys
    mode, out = sys.argv[1], sys.argv[2]
    from jtus import sharding
    if mode != "single":
        sharding.initialize(f"localhost:{sys.argv[3]}", 2, int(mode))
    import jax, jax.numpy as jnp, numpy as np, optax
    from jtus import losses, recipe, train
    from jtus.models import dlctus
    from tests import seqdata
    frames, targets = seqdata.to_jax(seqdata.sequence(T=4, B=4, h=8, w=8, factor=4))
    frames = frames._replace(reset=frames.reset.at[0].set(True))
    model = dlctus.make(dlctus.Config(factor=4))
    opt = optax.sgd(1.0)  # the update is the gradient (see test_sharding.py)
    step = train.make_train_step(model, losses.make("l1", 4), opt, loss_frames=2)
    params = model.init(jax.random.PRNGKey(0))
    ts = train.create_train_state(params, opt)
    if mode == "single":
        ts, _, st = step(ts, recipe.start_carry(model, frames, targets), frames, targets)
    else:
        assert jax.process_count() == 2 and len(jax.devices()) == 2
        p = jax.process_index()
        mine = jax.tree_util.tree_map(lambda x: x[:, 2 * p:2 * p + 2], (frames, targets))
        mesh = sharding.data_mesh(4)
        carry = sharding.shard(recipe.start_carry(model, *mine), mesh, axis=0)
        fr, tg = sharding.shard(mine, mesh, axis=1)
        assert fr.color.shape == (4, 4, 8, 8, 3) and not fr.color.is_fully_addressable
        ts = sharding.replicate(ts, mesh)
        ts, _, st = step(ts, carry, fr, tg)
    if sharding.is_main():
        host = sharding.to_host(ts.params)
        flat = {str(i): x for i, x in enumerate(jax.tree_util.tree_leaves(host))}
        moved = max(float(np.abs(a - b).max()) for a, b in zip(
            jax.tree_util.tree_leaves(host), jax.tree_util.tree_leaves(model.init(
                jax.random.PRNGKey(0)))))
        np.savez(out, loss=sharding.to_host(st["loss"]), moved=moved, **flat)
""")


def _port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _env():
    return dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT)


def _run_pair(argv_of, timeout=600):
    """Start processes 0 and 1 with ``argv_of(i)``; both must succeed."""
    procs = [subprocess.Popen(argv_of(i), cwd=ROOT, env=_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in (0, 1)]
    outs = [p.communicate(timeout=timeout) for p in procs]
    for p, (o, e) in zip(procs, outs):
        assert p.returncode == 0, e[-3000:]
    return outs


@pytest.mark.long
def test_two_processes_make_the_single_process_update(tmp_path):
    single, pair = tmp_path / "single.npz", tmp_path / "pair.npz"
    subprocess.run([sys.executable, "-c", STEP, "single", str(single)], cwd=ROOT, env=_env(),
                   check=True, timeout=600)
    port = str(_port())
    _run_pair(lambda i: [sys.executable, "-c", STEP, str(i), str(pair), port])
    a, b = np.load(single), np.load(pair)
    np.testing.assert_allclose(float(a["loss"]), float(b["loss"]), rtol=1e-6)
    params = [k for k in a.files if k not in ("loss", "moved")]
    # the step moved the parameters (not a comparison of two initializations)
    assert float(a["moved"]) > 1e-3 and float(b["moved"]) > 1e-3
    scale = float(a["moved"])
    for k in params:
        # gradient sums in a different order across the processes: float32 rounding
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=2e-5 * scale)


@pytest.mark.long
def test_train_cli_distributed_writes_one_run(tmp_path, tiny_data):
    work = tmp_path / "run"
    port = str(_port())
    _run_pair(lambda i: [sys.executable, "-m", "jtus.train", "--preset", "tiny", "--epochs", "1",
                         "--dataset", tiny_data, "--workdir", str(work), "--no-eval", "--quiet",
                         "--distributed", "--coordinator", f"localhost:{port}",
                         "--num-processes", "2", "--process-id", str(i)])
    hist = json.loads((work / "metrics.json").read_text())
    hist = hist["history"] if isinstance(hist, dict) else hist
    assert len(hist) == 1 and np.isfinite(hist[0]["train_loss"])
    assert (work / "checkpoint.msgpack").exists()
    assert not [p for p in work.iterdir() if p.name.startswith(".")]  # no temp files left


def test_train_cli_refuses_partial_distributed_flags(capsys):
    from jtus import train
    assert train.main(["--preset", "tiny", "--coordinator", "localhost:1"]) == 2
    assert "go together" in capsys.readouterr().err
