"""Colour-space transforms on the last axis (RGB in, RGB out)."""

from __future__ import annotations

import jax.numpy as jnp

# YCoCg as in the thesis (eq. 32-33), after Karis: Y in [0,1], Co, Cg in [-1/2, 1/2].
_RGB_TO_YCOCG = ((0.25, 0.5, 0.25), (0.5, 0.0, -0.5), (-0.25, 0.5, -0.25))
_YCOCG_TO_RGB = ((1.0, 1.0, -1.0), (1.0, 0.0, 1.0), (1.0, -1.0, -1.0))

# YCbCr, ITU-R BT.601 full range (JPEG): Cb, Cr offset by 1/2 into [0,1].
_KR, _KB = 0.299, 0.114
_KG = 1.0 - _KR - _KB


def _apply(m, x):
    return jnp.einsum("ij,...j->...i", jnp.asarray(m, x.dtype), x)


def rgb_to_ycocg(rgb):
    return _apply(_RGB_TO_YCOCG, rgb)


def ycocg_to_rgb(ycocg):
    return _apply(_YCOCG_TO_RGB, ycocg)


def rgb_to_ycbcr(rgb):
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    y = _KR * r + _KG * g + _KB * b
    cb = 0.5 + (b - y) / (2 * (1 - _KB))
    cr = 0.5 + (r - y) / (2 * (1 - _KR))
    return jnp.stack([y, cb, cr], -1)


def ycbcr_to_rgb(ycbcr):
    y, cb, cr = ycbcr[..., 0], ycbcr[..., 1] - 0.5, ycbcr[..., 2] - 0.5
    r = y + 2 * (1 - _KR) * cr
    b = y + 2 * (1 - _KB) * cb
    g = (y - _KR * r - _KB * b) / _KG
    return jnp.stack([r, g, b], -1)
