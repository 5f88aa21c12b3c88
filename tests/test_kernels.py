"""The trunk's three forms (``jtus.models.kernels``) against each other: the Pallas
kernels in Pallas's interpret mode on the CPU and the im2col matmuls, against the XLA
convolutions, to 1e-5 in float32, on images that meet the tiles' border on every side,
inside and in a DLCTUS step with gradients; and the kernels lowered for a CUDA GPU
through Pallas's Triton back end, which this CPU can do without a GPU."""

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


@pytest.mark.parametrize("size, tile", [((8, 8), kernels.TILE), ((20, 37), kernels.TILE),
                                        ((20, 37), (8, 16))])
def test_pallas_trunk_equals_the_xla_trunk(params, size, tile):
    """(8, 8): one tile, larger than the image; (20, 37): 2 x 2 tiles of the default
    size and 3 x 3 of (8, 16), ragged at the bottom and right, so every tile position
    and edge case of the clamped reads is met."""
    h = jnp.asarray(np.random.default_rng(0).normal(size=(2, *size, 32)), jnp.float32)
    args = kernels.stack_blocks(params, 4)
    got = jax.jit(lambda *a: kernels.trunk_pallas(*a, tile=tile, interpret=True))(*args, h)
    want = kernels.trunk_xla(*args, h)
    assert got.shape == want.shape and got.dtype == jnp.float32
    # float32; measured max 9.5e-7 on values up to 4.6
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-5)


def test_im2col_convolution_equals_the_xla_convolution():
    """Edge-padded, on a non-square image with distinct channel counts in and out, so
    that a transposed tap order or a wrong kernel reshape shows."""
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(2, 7, 9, 5)), jnp.float32)
    k = jnp.asarray(rng.normal(size=(3, 3, 5, 6)), jnp.float32)
    b = jnp.asarray(rng.normal(size=(6,)), jnp.float32)
    np.testing.assert_allclose(np.asarray(kernels.conv_im2col(x, k, b)),
                               np.asarray(layers.conv_edge(x, k, b)), rtol=0, atol=1e-5)


def test_pallas_trunk_lowers_to_triton_kernels_for_a_cuda_gpu(params):
    """Every operation of the kernel has a Triton lowering (power-of-two arrays, no
    value slicing): the trunk lowers for CUDA to eight Triton calls, one per
    convolution, in bfloat16 at 1080p 4x's size."""
    args = [a.astype(jnp.bfloat16) for a in kernels.stack_blocks(params, 4)]
    h = jax.ShapeDtypeStruct((1, 270, 480, 32), jnp.bfloat16)
    fn = jax.jit(lambda x: kernels.trunk_pallas(*args, x))
    text = fn.trace(h).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count("__gpu$xla.gpu.triton") == 8


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


@pytest.mark.parametrize("form", ["pallas", "im2col"])
def test_dlctus_step_with_each_trunk_form(params, form):
    """Three frames of DLCTUS with ``kernels=form`` equal the XLA path (outputs and
    history), and so do the parameter gradients of a loss over them."""
    frames, targets = seqdata.to_jax(seqdata.sequence(T=3, B=1, h=8, w=12, factor=4, seed=5))
    xla = dlctus.make(dlctus.Config())
    fused = dlctus.make(dlctus.Config(kernels=form))
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


def test_auto_picks_the_pallas_kernels_only_where_they_measured_faster():
    """``kernels="auto"`` (the default): the Pallas kernels on a GPU in bfloat16, XLA's
    convolutions in float32 and on a CPU; a named form is kept as named."""
    auto = dlctus.Config()
    assert auto.kernels == "auto"
    assert dlctus.Config(dtype="bfloat16").trunk_form("gpu") == "pallas"
    assert dlctus.Config(dtype="bfloat16").trunk_form("cuda") == "pallas"
    assert auto.trunk_form("gpu") == "xla" and auto.trunk_form("cpu") == "xla"
    assert dlctus.Config(dtype="bfloat16").trunk_form("cpu") == "xla"
    assert dlctus.Config(kernels="im2col", dtype="bfloat16").trunk_form("gpu") == "im2col"
    assert dlctus.Config(kernels="pallas").trunk_form("cpu") == "pallas"


def test_auto_differentiates_the_trunk_by_winograd_only_where_it_measured_faster(
        monkeypatch):
    """``conv_backward="auto"`` (the default): Winograd's F(4x4) forward and input
    gradient on a CPU in float32 or float64 for trunk maps within ``WINOGRAD_PIXELS`` per
    device, the custom backward on smaller and larger maps, in bfloat16 and on a GPU; a
    named form is kept as named. DLCTUS's network is then differentiated through
    ``layers.conv_edge_winograd``, each of its convolutions, only on a map in the
    range."""
    lo, hi = dlctus.WINOGRAD_PIXELS
    auto = dlctus.Config()
    assert auto.conv_backward == "auto"
    assert auto.conv_form("cpu") == "winograd"
    assert auto.conv_form("cpu", lo) == "winograd" and auto.conv_form("cpu", hi) == "winograd"
    assert auto.conv_form("cpu", lo - 1) == "custom" and auto.conv_form("cpu", hi + 1) == "custom"
    assert dlctus.Config(dtype="float64").conv_form("cpu", lo) == "winograd"
    assert dlctus.Config(dtype="bfloat16").conv_form("cpu", lo) == "custom"
    assert auto.conv_form("gpu", lo) == "custom"
    assert dlctus.Config(conv_backward="custom").conv_form("cpu", lo) == "custom"
    assert dlctus.Config(conv_backward="winograd").conv_form("cpu", hi + 1) == "winograd"
    assert dlctus.Config(conv_backward="winograd", dtype="bfloat16").conv_form("gpu") == \
        "winograd"
    calls = []
    real = layers.conv_edge_winograd
    monkeypatch.setattr(layers, "conv_edge_winograd", lambda *a: calls.append(1) or real(*a))
    config = dlctus.Config(blocks=1)  # one block: the same choice, a shorter compile
    params = dlctus.init(jax.random.PRNGKey(0), config)
    for side, winograd in ((16, False), (48, True), (91, False)):  # the trunk's map side
        x = dlctus.NetInput(lr=jnp.zeros((1, side, side, 4)), jitter=jnp.zeros((1, 2)),
                            hist=jnp.zeros((1, 4 * side, 4 * side, 4)))
        calls.clear()
        jax.jit(jax.grad(lambda p: jnp.mean(dlctus.network(p, x, config))))(params)
        assert len(calls) == (2 if winograd else 0), side


def test_kernels_config_is_checked():
    with pytest.raises(ValueError, match="kernels"):
        dlctus.Config(kernels="triton")
