"""The fused Pallas trunk (``jtus.models.kernels``) in Pallas's interpret mode on the
CPU, against the XLA path: values to 1e-5 in float32 on tiles that meet the image's
border on every side, inside and in a DLCTUS step, and gradients (its custom VJP)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import rollout
from jtus.models import dlctus, kernels, layers
from tests import seqdata


@pytest.fixture(scope="module")
def params():
    return dlctus.init(jax.random.PRNGKey(3))


@pytest.mark.parametrize("size", [(8, 8), (20, 37)])
def test_fused_trunk_equals_the_xla_trunk(params, size):
    """(8, 8): one tile, padded to the tile; (20, 37): 2 x 3 tiles, ragged at the
    bottom and right, so every tile position and border case is met."""
    h = jnp.asarray(np.random.default_rng(0).normal(size=(2, *size, 32)), jnp.float32)
    args = kernels.stack_blocks(params, 4)
    got = jax.jit(lambda *a: kernels.trunk_pallas(*a, interpret=True))(*args, h)
    want = kernels.trunk_xla(*args, h)
    assert got.shape == want.shape and got.dtype == jnp.float32
    # float32; measured max 9.5e-7 on values up to 4.6
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-5)


def test_xla_trunk_is_the_thesis_trunk(params):
    """The reference the kernel is checked against: four blocks of edge-padded 3x3
    convolution, ReLU, convolution, input added back, written here block by block."""
    h = jnp.asarray(np.random.default_rng(1).normal(size=(1, 6, 5, 32)), jnp.float32)
    want = h
    for i in range(4):
        blk = params[f"block{i + 1}"]
        r = jax.nn.relu(layers.conv_edge(want, blk["conv1"]["kernel"], blk["conv1"]["bias"]))
        want = want + layers.conv_edge(r, blk["conv2"]["kernel"], blk["conv2"]["bias"])
    got = kernels.trunk_xla(*kernels.stack_blocks(params, 4), h)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-6)


def test_dlctus_step_with_the_fused_trunk(params):
    """Three frames of DLCTUS with ``kernels="pallas"`` equal the XLA path (outputs and
    history), and so do the parameter gradients of a loss over them."""
    frames, targets = seqdata.to_jax(seqdata.sequence(T=3, B=1, h=8, w=12, factor=4, seed=5))
    xla = dlctus.make(dlctus.Config())
    fused = dlctus.make(dlctus.Config(kernels="pallas"))
    state = xla.init_state(seqdata.first(frames))

    def loss(model, p):
        outs, _ = rollout.outputs(model.step, p, state, frames)
        return jnp.mean(jnp.abs(outs - targets)), outs

    (l1, o1), g1 = jax.jit(jax.value_and_grad(lambda p: loss(xla, p), has_aux=True))(params)
    (l2, o2), g2 = jax.jit(jax.value_and_grad(lambda p: loss(fused, p), has_aux=True))(params)
    np.testing.assert_allclose(np.asarray(o2), np.asarray(o1), rtol=0, atol=1e-5)
    for a, b in zip(jax.tree_util.tree_leaves(g2), jax.tree_util.tree_leaves(g1)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    assert abs(float(l2) - float(l1)) < 1e-6


def test_kernels_config_is_checked():
    with pytest.raises(ValueError, match="kernels"):
        dlctus.Config(kernels="triton")
