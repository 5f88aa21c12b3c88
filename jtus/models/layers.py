"""Convolutions for the networks, NHWC / HWIO, written for XLA:CPU's fast paths.

``../shared/FINDINGS.md``: edge-padded VALID convolutions are 2-3x slower than SAME
ones on XLA:CPU, so a replicate-padded 3x3 convolution is computed as edge pad by
one, SAME convolution, crop by one (identical values, SAME speed).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

_DN = ("NHWC", "HWIO", "NHWC")


def conv(x, kernel, bias=None, stride=1, padding="SAME"):
    y = jax.lax.conv_general_dilated(x, kernel.astype(x.dtype), (stride, stride), padding,
                                     dimension_numbers=_DN)
    if bias is not None:
        y = y + bias.astype(y.dtype)
    return y


def conv_edge(x, kernel, bias=None):
    """Stride-1 convolution with replicate ('edge') padding of (k-1)/2, k odd."""
    k = kernel.shape[0]
    p = (k - 1) // 2
    xp = jnp.pad(x, ((0, 0), (p, p), (p, p), (0, 0)), mode="edge")
    return conv(xp, kernel, bias)[:, p:-p, p:-p, :] if p else conv(x, kernel, bias)


def torch_uniform_init(key, shape_hwio):
    """PyTorch's default Conv2d init: weights and bias ~ U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    kh, kw, ci, co = shape_hwio
    bound = 1.0 / math.sqrt(kh * kw * ci)
    kk, kb = jax.random.split(key)
    return {"kernel": jax.random.uniform(kk, shape_hwio, jnp.float32, -bound, bound),
            "bias": jax.random.uniform(kb, (co,), jnp.float32, -bound, bound)}
