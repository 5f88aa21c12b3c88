"""The train step with its batch split over two XLA CPU devices (``jax_num_cpu_devices``,
in a subprocess: JAX fixes its devices at start) gives the one-device update, and the
host-device count follows the cores and the batch."""

import os
import subprocess
import sys
import textwrap

from jtus import train

SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np, optax
    from jtus import losses, rollout, sharding, train
    from jtus.models import dlctus
    from tests import seqdata
    assert sharding.use_host_devices(2, batch=3) is None  # 2 does not divide 3: one device
    assert sharding.use_host_devices(3, batch=4) == 2     # the largest count that divides 4
    assert len(jax.devices()) == 2, jax.devices()
    assert sharding.use_host_devices(2) == 2              # started: the same count is fine
    assert sharding.use_host_devices(1) is None
    frames, targets = seqdata.to_jax(seqdata.sequence(T=4, B=4, h=8, w=8, factor=4))
    frames = frames._replace(reset=frames.reset.at[0].set(True))
    model = dlctus.make(dlctus.Config(factor=4))
    # Plain SGD with a unit rate: the update is the gradient, so the comparison below
    # measures the gradients. (Adam's first step, about lr * sign(g), turns the order
    # of the cross-device sum into visible moves wherever g is near zero.)
    opt = optax.sgd(1.0)
    # a loss with a log per crop: split crops must each keep their own term
    loss = losses.make("log-salvi", 4, temporal_weight=3.0)
    step = train.make_train_step(model, loss, opt, loss_frames=2)
    params = model.init(jax.random.PRNGKey(0))
    def carry():
        return rollout.start(model.init_state(jax.tree_util.tree_map(lambda x: x[0], frames)),
                             targets[0])
    copy = lambda: jax.tree_util.tree_map(jnp.copy, params)  # the step donates its state
    one, _, s1 = step(train.create_train_state(copy(), opt), carry(), frames, targets)
    mesh = sharding.data_mesh(4)
    step = train.make_train_step(model, loss, opt, loss_frames=2, mesh=mesh)
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


def test_two_devices_give_the_same_update():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=root, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "SAME UPDATE" in res.stdout


def test_training_splits_its_batch_from_crop_128_on():
    """The default device split: one per core from crops of 128 on (measured faster
    there), one device below (measured slower); ``--host-devices`` overrides both."""
    assert train.host_devices_for(64) == 1
    assert train.host_devices_for(128) is None and train.host_devices_for(256) is None
    assert train.host_devices_for(64, asked=2) == 2 and train.host_devices_for(256, asked=1) == 1


def test_mean_over_devices_is_pmean_of_each_array():
    """The gradients' exchange as one vector per dtype (``sharding.mean_over_devices``)
    gives, array by array, what one ``pmean`` per array gives: three members of a mapped
    axis stand in for devices (whose reduction XLA may order differently for a long
    vector than for a short array: 1 ulp, so float32 to 2e-7 and float64 to 1e-15
    relative); float32 and float64 arrays of several shapes and an integer array
    (exact), in nested trees."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jtus import sharding

    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        trees = [{"k": rng.normal(size=(3, 3, 3, 2, 4)).astype(np.float32),
                  "b": rng.normal(size=(3, 4)).astype(np.float32)},
                 rng.normal(size=(3, 5)),  # float64
                 (rng.integers(0, 9, size=(3, 2)), rng.normal(size=(3,)).astype(np.float32))]

        def each(*t):
            return jax.tree_util.tree_map(lambda x: jax.lax.pmean(x, "data"), list(t))

        def flat(*t):
            return list(sharding.mean_over_devices(list(t)))

        want = jax.vmap(each, axis_name="data")(*trees)
        got = jax.vmap(flat, axis_name="data")(*trees)
        assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(want)
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            assert a.dtype == b.dtype and a.shape == b.shape
            rtol = {np.float32: 2e-7, np.float64: 1e-15}.get(a.dtype.type, 0)
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=0)
        # the members hold the mean, not their own values
        assert not np.allclose(np.asarray(want[1][0]), trees[1][0])
        assert jnp.allclose(want[1][0], trees[1].mean(0))
