"""Convolutions for the networks, NHWC / HWIO, written for XLA:CPU's fast paths.

On XLA:CPU edge-padded VALID convolutions are 4-5x slower than SAME ones (no XLA flag
helps: oneDNN, XNNPACK, the thunk runtime and Eigen threading were tried), so a
replicate-padded 3x3 convolution is computed as the zero-padded SAME convolution plus
the terms of the replicated one-pixel border ring (``conv_edge``), and, where its
padded input is kept for a backward pass, as edge pad by one, SAME convolution, crop by
one. ``python experiments/conv_padding.py`` measures the ways (docs/performance.md).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from jtus.models import winograd
from jtus.sampling import pad_edge

_DN = ("NHWC", "HWIO", "NHWC")
# how a model's convolutions are differentiated (its ``Config.conv_backward``): "custom"
# (the ``*_fast`` backward), "winograd" (F(4x4, 3x3) forward and input gradient),
# "autodiff" (JAX's own); "auto": the model picks by measurement (its ``conv_form``)
CONV_BACKWARDS = ("auto", "autodiff", "custom", "winograd")


def conv(x, kernel, bias=None, stride=1, padding="SAME"):
    y = jax.lax.conv_general_dilated(x, kernel.astype(x.dtype), (stride, stride), padding,
                                     dimension_numbers=_DN)
    if bias is not None:
        y = y + bias.astype(y.dtype)
    return y


def _conv_edge_padded(x, kernel, bias):
    """``(conv_edge(x, kernel, bias), the edge-padded input)``."""
    p = (kernel.shape[0] - 1) // 2
    if not p:
        return conv(x, kernel, bias), x
    xp = pad_edge(x, p)
    return conv(xp, kernel, bias)[:, p:-p, p:-p, :], xp


def conv_edge(x, kernel, bias=None):
    """Stride-1 convolution with replicate ('edge') padding of (k-1)/2, k odd.

    A 3x3 kernel runs as the SAME (zero-padded) convolution plus ``edge_ring``: no
    padded copy of ``x`` is made and none of the output is cropped, and XLA fuses the
    ring's masks with the bias (and whatever elementwise work follows) into one pass;
    DLCTUS's trunk took 0.73x the time of edge pad + SAME + crop at 1080p and 0.84x at
    720p on a 2-core Intel Xeon (``python experiments/conv_padding.py``,
    docs/results/conv_padding/). Other kernel sizes pad, convolve and crop."""
    if kernel.shape[:2] == (3, 3):
        return conv(x, kernel, bias) + edge_ring(x, kernel.astype(x.dtype))
    return _conv_edge_padded(x, kernel, bias)[0]


def edge_ring(x, kernel):
    """``conv_edge(x, kernel) - conv(x, kernel)`` for a 3x3 ``kernel``: the taps that fall
    on the one-pixel ring of replicated border pixels around ``x [B,H,W,C]``, which zero
    padding leaves out. The ring's top row (its corners included) meets only kernel row 0
    at output row 0, its bottom row kernel row 2 at row H-1, its left column (corners
    excluded) kernel column 0 at column 0 and its right column kernel column 2 at column
    W-1: four 1-D convolutions of border lines, each three small matmuls, placed on the
    output's border by broadcast masks."""
    h, w = x.shape[1:3]

    def line(v):  # [B,n,C] -> [B,n+2,C], the line's own ends replicated
        return jnp.concatenate([v[:, :1], v, v[:, -1:]], 1)

    def inner(v):  # [B,n,C] -> [B,n+2,C], zeros at the ends (those are corners)
        z = jnp.zeros_like(v[:, :1])
        return jnp.concatenate([z, v, z], 1)

    def conv1d(v, taps, n):  # taps [3,C,O] along the line
        return sum(v[:, d:d + n] @ taps[d] for d in range(3))

    top = conv1d(line(x[:, 0]), kernel[0], w)        # [B,W,O]
    bottom = conv1d(line(x[:, -1]), kernel[2], w)
    left = conv1d(inner(x[:, :, 0]), kernel[:, 0], h)  # [B,H,O]
    right = conv1d(inner(x[:, :, -1]), kernel[:, 2], h)
    row = jnp.arange(h)[:, None, None]
    col = jnp.arange(w)[:, None]
    return (jnp.where(row == 0, top[:, None], 0) + jnp.where(row == h - 1, bottom[:, None], 0)
            + jnp.where(col == 0, left[:, :, None], 0)
            + jnp.where(col == w - 1, right[:, :, None], 0))


def scale_inputs(conv, channels, factor):
    """Convolution ``conv`` (``{"kernel": HWIO, "bias"}``) with the weights that read
    input ``channels`` multiplied by ``factor`` (the others as they are)."""
    n = conv["kernel"].shape[2]
    scale = jnp.ones((n,), jnp.float32).at[jnp.asarray(list(channels))].set(factor)
    return {**conv, "kernel": conv["kernel"] * scale[:, None]}


def uniform(key, shape, bound):
    """``jax.random.uniform(key, shape, float32, -bound, bound)``, drawn as the first
    ``prod(shape)`` values of a draw whose length is a power of two. With JAX's
    partitionable threefry (its default) value i of a draw depends only on the key and
    i, so the values are the same; but op by op each new length compiles its own
    threefry program (1-3 s on this CPU), and rounding the lengths up lets a model's
    layers share a few: KPN's init took 51 s and NSRR-fast's 105 s of a loaded core."""
    if not jax.config.jax_threefry_partitionable:
        return jax.random.uniform(key, shape, jnp.float32, -bound, bound)
    n = math.prod(shape)
    flat = jax.random.uniform(key, (1 << max(n - 1, 0).bit_length(),), jnp.float32,
                              -bound, bound)
    return flat[:n].reshape(shape)


def torch_uniform_init(key, shape_hwio):
    """PyTorch's default Conv2d init: weights and bias ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    kh, kw, ci, co = shape_hwio
    bound = 1.0 / math.sqrt(kh * kw * ci)
    kk, kb = jax.random.split(key)
    return {"kernel": uniform(kk, shape_hwio, bound), "bias": uniform(kb, (co,), bound)}


def _edge_pad_adjoint(g, p):
    """Adjoint of edge padding by ``p`` on H and W: fold the border back onto the edge.
    ``pad_edge`` transposed by JAX (slices of ``g`` summed), which XLA:CPU fuses better
    than adding the border rows and columns in place: the trunk's training gradient took
    0.92-0.95x the time (``python experiments/conv_padding.py --train``,
    docs/results/conv_padding-train-in-place-adjoint/)."""
    b, h, w, c = g.shape
    inner = jax.ShapeDtypeStruct((b, h - 2 * p, w - 2 * p, c), g.dtype)
    return jax.linear_transpose(lambda v: pad_edge(v, p), inner)(g)[0]


@jax.custom_vjp
def conv_edge_fast(x, kernel, bias):
    """``conv_edge`` with a backward pass made of standard-layout ops only.

    On XLA:CPU the autodiff backward of a convolution inside a rolled ``lax.scan``
    falls back to a slow path (14x slower training step, docs/performance.md). Here the
    kernel gradient is a VALID convolution of the padded input (channels as batch)
    with the output gradient as its kernel, and the input gradient a SAME convolution
    with the flipped, transposed kernel followed by the adjoint of the edge padding,
    all in standard NHWC/HWIO layout through explicit transposes. The padded input is
    the saved residual, so the backward does not pad again: under differentiation the
    forward pads, convolves and crops (``conv_edge``'s ring form, which saves ``x``
    instead, made the training step no faster with this backward and slower with the
    ring's own), and without differentiation it is ``conv_edge``. Values and gradients
    equal ``conv_edge``'s (tested in float64).
    """
    return conv_edge(x, kernel, bias)


def _fast_fwd(x, kernel, bias):
    y, xp = _conv_edge_padded(x, kernel, bias)
    return y, (xp, kernel)


def _edge_bwd(res, g, full):
    """The three gradients of an edge-padded convolution whose padded input ``xp`` was
    kept: the kernel's by ``_kernel_grad``, the input's as ``full(g, flipped kernel)``
    (the gradient with respect to ``xp``) folded back through the padding."""
    xp, kernel = res
    p = (kernel.shape[0] - 1) // 2
    dk = _kernel_grad(xp, g)
    flipped = jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2).astype(g.dtype)
    dxp = full(g, flipped)
    dx = _edge_pad_adjoint(dxp, p) if p else dxp
    return dx.astype(xp.dtype), dk.astype(kernel.dtype), g.sum((0, 1, 2)).astype(kernel.dtype)


def _full_xla(g, flipped):
    """The "full" convolution of ``g`` (output larger by the kernel's reach): a SAME
    convolution of ``g`` zero-padded by that reach."""
    p = (flipped.shape[0] - 1) // 2
    return conv(jnp.pad(g, ((0, 0), (p, p), (p, p), (0, 0))), flipped)


def _fast_bwd(res, g):
    return _edge_bwd(res, g, _full_xla)


conv_edge_fast.defvjp(_fast_fwd, _fast_bwd)


@jax.custom_vjp
def conv_edge_winograd(x, kernel, bias):
    """``conv_edge_fast`` (3x3 kernels) whose forward pass and input gradient under
    differentiation are Winograd's F(4x4, 3x3) (``winograd.conv3x3_valid``; the kernel
    gradient is ``conv_edge_fast``'s). Without differentiation it is ``conv_edge``. On
    XLA:CPU, DLCTUS's training step with it took 0.89-0.93x the time with
    ``conv_edge_fast`` (docs/performance.md, "Winograd's convolutions in training"). Values
    and gradients equal ``conv_edge``'s to float32 rounding (F(4x4)'s: about 1e-6 of the
    largest value) and to 1e-10 in float64 (tested)."""
    return conv_edge(x, kernel, bias)


def _winograd_biased(name, xp, kernel, bias):
    """``name``'s forward pass under differentiation: the VALID 3x3 convolution of the
    padded ``xp`` by ``winograd.conv3x3_valid``, plus the bias; other kernels refused."""
    if kernel.shape[:2] != (3, 3):
        raise ValueError(f"kernel: {name} takes 3x3 kernels, got shape {kernel.shape}")
    return winograd.conv3x3_valid(xp, kernel.astype(xp.dtype)) + bias.astype(xp.dtype)


def _winograd_fwd(x, kernel, bias):
    xp = pad_edge(x, 1)
    return _winograd_biased("conv_edge_winograd", xp, kernel, bias), (xp, kernel)


def _full_winograd(g, flipped):
    return winograd.conv3x3_valid(jnp.pad(g, ((0, 0), (2, 2), (2, 2), (0, 0))), flipped)


def _winograd_bwd(res, g):
    return _edge_bwd(res, g, _full_winograd)


conv_edge_winograd.defvjp(_winograd_fwd, _winograd_bwd)


KERNEL_GRAD_FORMS = {"conv": "convolution", "taps": "matmul per tap",
                     "columns": "matmul per column"}


def kernel_grad_form(kernel_size, h, w, c_in, c_out):
    """How ``_kernel_grad`` computes the gradient of a ``kernel_size`` square kernel over
    an ``h x w`` map from ``c_in`` to ``c_out`` channels (a key of ``KERNEL_GRAD_FORMS``):

    - ``"taps"``, one matmul per kernel tap: 3x3 kernels from 32 or more channels to 16
      or more on 128x128 maps or larger, and from 128 or more channels on 64x64 maps;
    - ``"columns"``, one matmul per kernel column, on the other maps of 64x64 or more
      to 32 or more channels that are not a multiple of 16 (KPN's 5x5 layer to 50
      channels), where the convolution form falls off XLA:CPU's fast path (2.7x the
      column form's time alone; KPN's training step about 0.96x with it);
    - ``"conv"``, the convolution, everywhere else (small maps, DLCTUS's 32x32 trunk,
      few channels out, multiples of 16 out). Timed alone, the column form was faster
      on two of NSRR's layers too (its 64x64 level, its reweighting's first layer), but
      NSRR's and NSRR-fast's training steps with it there were no faster, within the
      spread of identical programs timed side by side.

    Set by ``python experiments/kernel_grad.py`` (docs/results/kernel-grad/), which times
    the three at DLCTUS's, NSRR's and KPN's training shapes."""
    big = h * w >= 128 * 128 or (h * w >= 64 * 64 and c_in >= 128)
    if kernel_size == 3 and c_in >= 32 and c_out >= 16 and big:
        return "taps"
    if c_out >= 32 and c_out % 16 and h * w >= 64 * 64:
        return "columns"
    return "conv"


def _kernel_grad(xp, g):
    """``dk[dy,dx,c,o] = sum_{b,y,x} xp[b,y+dy,x+dx,c] g[b,y,x,o]``, the kernel gradient
    of a stride-1 VALID convolution of ``xp``, in the form ``kernel_grad_form`` picks.

    On small maps (DLCTUS's trunk, 32x32 at crop 128) it is itself a VALID convolution,
    channels as its batch and the batch as its features, with ``g`` as a ``[h,w,B,o]``
    kernel: in NHWC/HWIO layout (explicit transposes) XLA:CPU runs it 1.4x faster than
    one matmul per kernel tap, whose ``[B*h*w,C]^T [B*h*w,C]`` shape it does at half the
    rate of a convolution (docs/results/cpu-speed/result.md, "Training speed"). On larger
    maps that convolution's ``h x w`` kernel is slow, the more so the more channels it
    writes: from 32 or more input channels on 128x128 maps (NSRR's U-Net) one matmul per
    tap of ``xp`` as it is, with ``g`` shifted into a zero-padded copy, is faster, and
    to channel counts off XLA:CPU's fast path (KPN's 5x5 kernel layer to 50) one matmul
    per kernel column of the row-shifted copies of ``xp``."""
    form = kernel_grad_form(xp.shape[1] - g.shape[1] + 1, g.shape[1], g.shape[2],
                            xp.shape[-1], g.shape[-1])
    if form == "taps":
        return kernel_grad_matmuls(xp, g)
    if form == "columns":
        return kernel_grad_columns(xp, g)
    return kernel_grad_conv(xp, g)


def kernel_grad_conv(xp, g):
    """``_kernel_grad`` as one VALID convolution, channels as the batch."""
    dk = jax.lax.conv_general_dilated(xp.transpose(3, 1, 2, 0),
                                      g.astype(xp.dtype).transpose(1, 2, 0, 3), (1, 1),
                                      "VALID", dimension_numbers=_DN)
    return dk.transpose(1, 2, 0, 3)


def kernel_grad_columns(xp, g):
    """``_kernel_grad`` as one matmul per kernel column: the ``kh`` row-shifted views of
    ``xp`` at that column's offset, side by side as ``kh * C`` channels, contracted
    with ``g`` over every pixel: ``[B*h*w, kh*C]^T [B*h*w, o]``."""
    b, h, w, o = g.shape
    kh, kw = xp.shape[1] - h + 1, xp.shape[2] - w + 1
    g2 = g.astype(xp.dtype).reshape(-1, o)
    cols = []
    for dx in range(kw):
        rows = jnp.concatenate([xp[:, dy:dy + h, dx:dx + w] for dy in range(kh)], -1)
        cols.append(jax.lax.dot_general(rows.reshape(-1, rows.shape[-1]), g2,
                                        (((0,), (0,)), ((), ()))).reshape(kh, -1, o))
    return jnp.stack(cols, 1)


def kernel_grad_matmuls(xp, g):
    """``_kernel_grad`` as one ``xp^T g_shifted`` matmul per kernel tap, ``g`` placed at
    the tap's offset in a zero-padded copy the size of ``xp``."""
    b, h, w, o = g.shape
    kh, kw = xp.shape[1] - h + 1, xp.shape[2] - w + 1
    x2 = xp.reshape(-1, xp.shape[-1])
    g = g.astype(xp.dtype)
    taps = [jax.lax.dot_general(x2, jnp.pad(g, ((0, 0), (dy, kh - 1 - dy), (dx, kw - 1 - dx),
                                                 (0, 0))).reshape(-1, o),
                                (((0,), (0,)), ((), ())))
            for dy in range(kh) for dx in range(kw)]
    return jnp.stack(taps).reshape(kh, kw, xp.shape[-1], o)


@jax.custom_vjp
def conv_same_fast(x, kernel, bias):
    """``conv(x, kernel, bias)`` (SAME zero padding, stride 1, odd kernel) with the
    standard-layout backward of ``conv_edge_fast``: inside a rolled ``lax.scan``
    (recurrent models' training) XLA:CPU's autodiff backward of a convolution takes a
    slow path. Values and gradients equal ``conv``'s (tested in float64)."""
    return conv(x, kernel, bias)


def _same_fwd(x, kernel, bias):
    return conv(x, kernel, bias), (x, kernel)


def _same_grads(res, g, same):
    """The three gradients of a zero-padded SAME convolution whose input ``x`` was kept:
    the kernel's by ``_kernel_grad`` of the padded input, the input's as ``same(g,
    flipped kernel)``, a SAME convolution (the adjoint of a zero-padded SAME one)."""
    x, kernel = res
    p = (kernel.shape[0] - 1) // 2
    q = (kernel.shape[1] - 1) // 2
    xp = jnp.pad(x, ((0, 0), (p, p), (q, q), (0, 0)))
    dk = _kernel_grad(xp, g)
    flipped = jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2).astype(g.dtype)
    dx = same(g, flipped)
    return dx.astype(x.dtype), dk.astype(kernel.dtype), g.sum((0, 1, 2)).astype(kernel.dtype)


def _same_bwd(res, g):
    return _same_grads(res, g, conv)


conv_same_fast.defvjp(_same_fwd, _same_bwd)


@jax.custom_vjp
def conv_same_winograd(x, kernel, bias):
    """``conv_same_fast`` (3x3 kernels) whose forward pass and input gradient under
    differentiation are Winograd's F(4x4, 3x3) (``winograd.conv3x3_valid`` of the
    zero-padded input and of the zero-padded output gradient); the kernel gradient is
    ``conv_same_fast``'s. Without differentiation it is ``conv``. NSRR's training step
    took 0.97x the time with it on its wide layers (``nsrr.Config.conv_form``,
    docs/performance.md). Values and gradients equal ``conv``'s to float32 rounding
    (about 1e-6 of the largest value) and to 1e-10 in float64 (tested)."""
    return conv(x, kernel, bias)


def _zero_pad1(x):
    return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))


def _same_winograd_fwd(x, kernel, bias):
    return _winograd_biased("conv_same_winograd", _zero_pad1(x), kernel, bias), (x, kernel)


def _same_winograd(x, kernel):
    """The SAME 3x3 convolution by Winograd's F(4x4, 3x3): VALID on ``x`` zero-padded."""
    return winograd.conv3x3_valid(_zero_pad1(x), kernel)


def _same_winograd_bwd(res, g):
    return _same_grads(res, g, _same_winograd)


conv_same_winograd.defvjp(_same_winograd_fwd, _same_winograd_bwd)


def conv_same(x, p, stride=1, form="custom"):
    """A zero-padded ('SAME') convolution with a ``{"kernel", "bias"}`` dict, differentiated
    as ``form`` (one of ``CONV_BACKWARDS`` but ``"auto"``, which a model resolves):
    ``"custom"``, stride 1 with an odd kernel through ``conv_same_fast``; ``"winograd"``,
    stride 1 with a 3x3 kernel through ``conv_same_winograd`` (other kernels as
    ``"custom"``); ``"autodiff"``, ``conv`` as JAX differentiates it. Every form has the
    same value without differentiation."""
    if form not in CONV_BACKWARDS[1:]:
        raise ValueError(f"form: expected one of {CONV_BACKWARDS[1:]}, got {form!r}")
    k, b = p["kernel"], p.get("bias")
    if form != "autodiff" and stride == 1 and b is not None:
        if form == "winograd" and k.shape[:2] == (3, 3):
            return conv_same_winograd(x, k, b)
        if k.shape[0] % 2 and k.shape[1] % 2:
            return conv_same_fast(x, k, b)
    return conv(x, k, b, stride=stride)


def mlp_init(key, sizes):
    """Dense layers ``[{"kernel": [i, o], "bias": [o]}]`` with PyTorch's Linear init."""
    keys = jax.random.split(key, len(sizes) - 1)
    out = []
    for k, (i, o) in zip(keys, zip(sizes[:-1], sizes[1:])):
        bound = 1.0 / math.sqrt(i)
        kk, kb = jax.random.split(k)
        out.append({"kernel": uniform(kk, (i, o), bound), "bias": uniform(kb, (o,), bound)})
    return out
