"""The train step on two (forced host) devices gives the one-device update."""

import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np, optax
    from jtus import losses, rollout, sharding, train
    from jtus.models import dlctus
    from tests import seqdata
    assert len(jax.devices()) == 2, jax.devices()
    frames, targets = seqdata.to_jax(seqdata.sequence(T=4, B=4, h=8, w=8, factor=4))
    frames = frames._replace(reset=frames.reset.at[0].set(True))
    model = dlctus.make(dlctus.Config(factor=4))
    # Plain SGD with a unit rate: the update is the gradient, so the comparison below
    # measures the gradients. (Adam's first step, about lr * sign(g), turns the order
    # of the cross-device sum into visible moves wherever g is near zero.)
    opt = optax.sgd(1.0)
    step = train.make_train_step(model, losses.make("l1", 4), opt, loss_frames=2)
    params = model.init(jax.random.PRNGKey(0))
    def carry():
        return rollout.start(model.init_state(jax.tree_util.tree_map(lambda x: x[0], frames)),
                             targets[0])
    copy = lambda: jax.tree_util.tree_map(jnp.copy, params)  # the step donates its state
    one, _, s1 = step(train.create_train_state(copy(), opt), carry(), frames, targets)
    mesh = sharding.data_mesh(4)
    ts = sharding.replicate(train.create_train_state(copy(), opt), mesh)
    fr, tg = sharding.shard((frames, targets), mesh, axis=1)
    assert len(fr.color.sharding.device_set) == 2
    two, _, s2 = step(ts, sharding.shard(carry(), mesh, axis=0), fr, tg)
    np.testing.assert_allclose(float(s1["loss"]), float(s2["loss"]), rtol=1e-6)
    upd = [np.asarray(a) - np.asarray(p) for a, p in zip(jax.tree_util.tree_leaves(one.params),
                                                        jax.tree_util.tree_leaves(params))]
    scale = max(float(np.abs(u).max()) for u in upd)
    # the step moved the parameters by more than float32's spacing at their size (~4e-9)
    assert scale > 1e-3, scale
    for a, b in zip(jax.tree_util.tree_leaves(one.params), jax.tree_util.tree_leaves(two.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2e-5 * scale)
    np.testing.assert_allclose(float(s1["grad_norm"]), float(s2["grad_norm"]), rtol=1e-5)
    print("SAME UPDATE")
""")


@pytest.mark.long
def test_two_devices_give_the_same_update():
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=(
        os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip())
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=root, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "SAME UPDATE" in res.stdout
