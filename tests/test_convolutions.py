"""The networks' convolutions (``jtus.models.layers``, ``jtus.models.winograd``):
replicate-padded ones against an independent form, ``jnp.pad(mode="edge")`` followed by
a VALID convolution; the custom backwards' kernel gradient forms against autodiff; the
Winograd convolutions against XLA's."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jtus.models import layers, winograd


def _reference(x, k, b):
    p = (k.shape[0] - 1) // 2
    xp = jnp.pad(x, ((0, 0), (p, p), (p, p), (0, 0)), mode="edge")
    return layers.conv(xp, k, b, padding="VALID")


def _draw(rng, shape, ksize, c_in=3, c_out=4, dtype=np.float64):
    x = rng.normal(size=(2, *shape, c_in)).astype(dtype)
    k = rng.normal(size=(ksize, ksize, c_in, c_out)).astype(dtype)
    b = rng.normal(size=(c_out,)).astype(dtype)
    return jnp.asarray(x), jnp.asarray(k), jnp.asarray(b)


# one-pixel-high and -wide images: the ring's top and bottom rows (or left and right
# columns) land on the same output line
@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (6, 1), (2, 2), (5, 7)])
@pytest.mark.parametrize("ksize", [3, 5])
def test_conv_edge_equals_edge_pad_then_valid_float64(x64, rng, shape, ksize):
    x, k, b = _draw(rng, shape, ksize)
    want = _reference(x, k, b)
    for fn in (layers.conv_edge, layers.conv_edge_fast):
        got = fn(x, k, b)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)


def test_conv_edge_gradients_float64(x64, rng):
    """The ring form's autodiff gradients (x, kernel, bias) match finite differences, and
    ``conv_edge_fast``'s hand-written backward matches them."""
    x, k, b = _draw(rng, (4, 5), 3)
    check_grads(layers.conv_edge, (x, k, b), order=1, modes=("rev",), eps=1e-6,
                atol=1e-7, rtol=1e-7)
    g = jnp.asarray(rng.normal(size=(2, 4, 5, 4)))
    _, vjp_auto = jax.vjp(layers.conv_edge, x, k, b)
    _, vjp_fast = jax.vjp(layers.conv_edge_fast, x, k, b)
    for a, c in zip(vjp_auto(g), vjp_fast(g)):
        np.testing.assert_allclose(c, a, rtol=1e-12, atol=1e-12)


def test_conv_edge_fast_forward_under_differentiation_equals_its_value(rng):
    """Under ``jax.vjp`` the forward pads, convolves and crops; without it, the ring form
    runs: in float32 the two differ only by rounding (1e-5 here)."""
    x, k, b = _draw(rng, (9, 11), 3, 32, 32, np.float32)
    plain = jax.jit(layers.conv_edge_fast)(x, k, b)
    under_vjp, _ = jax.vjp(layers.conv_edge_fast, x, k, b)
    np.testing.assert_allclose(under_vjp, plain, rtol=0, atol=1e-5 * float(jnp.abs(plain).max()))


@pytest.mark.parametrize("kernel,side,c_in,c_out,form", [(3, 8, 3, 4, "conv"),
                                                          (3, 128, 32, 16, "taps"),
                                                          (5, 64, 4, 40, "columns")])
def test_kernel_gradient_forms_equal_autodiff_float64(x64, rng, kernel, side, c_in, c_out,
                                                      form):
    """``kernel_grad_conv``, ``kernel_grad_matmuls`` and ``kernel_grad_columns`` give
    autodiff's kernel gradient of a VALID convolution, and the custom backwards
    (``conv_same_fast``, ``conv_edge_fast``) the kernel gradient of plain autodiff, on a
    map where each form is the one chosen."""
    p = kernel // 2
    xp = jnp.asarray(rng.normal(size=(2, side + 2 * p, side + 2 * p, c_in)))
    g = jnp.asarray(rng.normal(size=(2, side, side, c_out)))
    k = jnp.asarray(rng.normal(size=(kernel, kernel, c_in, c_out)))
    b = jnp.asarray(rng.normal(size=(c_out,)))
    _, vjp = jax.vjp(lambda k: layers.conv(xp, k, padding="VALID"), k)
    want = vjp(g)[0]
    for fn in (layers.kernel_grad_conv, layers.kernel_grad_matmuls, layers.kernel_grad_columns):
        np.testing.assert_allclose(fn(xp, g), want, rtol=1e-12, atol=1e-10)
    assert layers.kernel_grad_form(kernel, side, side, c_in, c_out) == form
    x = xp[:, p:side + p, p:side + p]
    for fast, plain in ((layers.conv_same_fast, layers.conv), (layers.conv_edge_fast, _reference)):
        got = jax.vjp(lambda k: fast(x, k, b), k)[1](g)[0]
        ref = jax.vjp(lambda k: plain(x, k, b), k)[1](g)[0]
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-10)


# output sizes below, equal to and off a multiple of the tile (the last tiles overhang)
@pytest.mark.parametrize("m", [2, 4])
@pytest.mark.parametrize("shape", [(1, 1), (4, 4), (5, 9)])
def test_winograd_valid_convolution_equals_xla_float64(x64, rng, m, shape):
    """``winograd.conv3x3_valid`` is the VALID cross-correlation of XLA's convolution op,
    for F(2x2) and F(4x4), on sizes that no tile divides."""
    xp = jnp.asarray(rng.normal(size=(2, shape[0] + 2, shape[1] + 2, 5)))
    k = jnp.asarray(rng.normal(size=(3, 3, 5, 7)))
    got = jax.jit(winograd.conv3x3_valid, static_argnums=2)(xp, k, m)
    want = layers.conv(xp, k, padding="VALID")
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_winograd_rejects_what_it_cannot_compute(rng):
    x = jnp.zeros((1, 6, 6, 2))
    with pytest.raises(ValueError, match="m: expected one of"):
        winograd.conv3x3_valid(x, jnp.zeros((3, 3, 2, 2)), m=3)
    with pytest.raises(ValueError, match=r"kernel: expected a \[3,3,C,O\] kernel"):
        winograd.conv3x3_valid(x, jnp.zeros((5, 5, 2, 2)))
    with pytest.raises(ValueError, match="xp: expected at least 3x3 pixels"):
        winograd.conv3x3_valid(jnp.zeros((1, 2, 6, 2)), jnp.zeros((3, 3, 2, 2)))
    with pytest.raises(ValueError, match="conv_edge_winograd takes 3x3 kernels"):
        jax.vjp(layers.conv_edge_winograd, x, jnp.zeros((5, 5, 2, 2)), jnp.zeros(2))
    with pytest.raises(ValueError, match="conv_same_winograd takes 3x3 kernels"):
        jax.vjp(layers.conv_same_winograd, x, jnp.zeros((5, 5, 2, 2)), jnp.zeros(2))
    with pytest.raises(ValueError, match=r"form: expected one of \('autodiff', 'custom', "
                                         r"'winograd'\), got 'auto'"):
        layers.conv_same(x, {"kernel": jnp.zeros((3, 3, 2, 2)), "bias": jnp.zeros(2)},
                         form="auto")


# (Winograd form, its reference, map, channels in, out): the edge-padded trunk's at
# DLCTUS's width, the zero-padded one on a map no tile divides
WINOGRAD_FORMS = [(layers.conv_edge_winograd, layers.conv_edge, (6, 9), 32, 32),
                  (layers.conv_same_winograd, layers.conv, (7, 10), 32, 16)]


@pytest.mark.parametrize("fn,ref,shape,c_in,c_out", WINOGRAD_FORMS)
def test_winograd_forms_equal_their_convolution_float64(x64, rng, fn, ref, shape, c_in,
                                                        c_out):
    """``conv_edge_winograd`` and ``conv_same_winograd``: the value, the forward under
    differentiation and the three gradients are those of the convolution each stands
    for (1e-10), and the gradients match finite differences."""
    x, k, b = _draw(rng, shape, 3, c_in, c_out)
    g = jnp.asarray(rng.normal(size=(2, *shape, c_out)))
    # each function jitted: one program each way rather than one per operation
    want, vjp_ref = jax.vjp(jax.jit(ref), x, k, b)
    np.testing.assert_allclose(fn(x, k, b), want, rtol=0, atol=1e-13)
    got, vjp = jax.vjp(jax.jit(fn), x, k, b)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
    for a, c in zip(vjp(g), vjp_ref(g)):
        np.testing.assert_allclose(a, c, rtol=1e-10, atol=1e-10)
    x, k, b = _draw(rng, (5, 3), 3)
    check_grads(jax.jit(fn), (x, k, b), order=1, modes=("rev",), eps=1e-6, atol=1e-7,
                rtol=1e-7)


@pytest.mark.parametrize("fn,direct,side,width,scale", [
    (layers.conv_edge_winograd, layers.conv_edge_fast, 32, 32, 0.1),   # DLCTUS's trunk
    (layers.conv_same_winograd, layers.conv_same_fast, 64, 64, 0.05)])  # NSRR's U-Net
def test_winograd_forms_float32_within_rounding_of_the_direct_convolution(rng, fn, direct,
                                                                         side, width, scale):
    """In float32 F(4x4)'s transforms round differently from XLA's convolution: the
    forward under differentiation and the input gradient stay within 1e-5 of the
    largest value, at DLCTUS's trunk width and NSRR's U-Net width on training map sizes."""
    x, k, b = _draw(rng, (side, side), 3, width, width, np.float32)
    k = k * scale
    g = jnp.asarray(rng.normal(size=(2, side, side, width)).astype(np.float32))
    want, vjp_ref = jax.vjp(jax.jit(direct), x, k, b)
    got, vjp = jax.vjp(jax.jit(fn), x, k, b)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * float(jnp.abs(want).max()))
    for a, c in zip(vjp(g), vjp_ref(g)):
        np.testing.assert_allclose(a, c, rtol=0, atol=1e-5 * float(jnp.abs(c).max()))


def test_conv_same_forms_have_one_value_and_one_gradient_float64(x64, rng):
    """``conv_same``'s forms (``"custom"``, ``"winograd"``, ``"autodiff"``) compute the same
    convolution and the same gradients, for the 3x3 kernel Winograd takes and for a 5x5
    one, which it leaves to the custom backward."""
    for ksize in (3, 5):
        x, k, b = _draw(rng, (6, 5), ksize, 4, 3)
        p = {"kernel": k, "bias": b}
        grads = {form: jax.grad(lambda x, p, form=form: jnp.sum(
            jnp.sin(layers.conv_same(x, p, form=form))), (0, 1))(x, p)
                 for form in ("custom", "winograd", "autodiff")}
        for form in ("custom", "winograd"):
            for a, c in zip(jax.tree_util.tree_leaves(grads[form]),
                            jax.tree_util.tree_leaves(grads["autodiff"])):
                np.testing.assert_allclose(a, c, rtol=1e-10, atol=1e-10)
