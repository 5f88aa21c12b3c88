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


# ---------------------------------------------------------------- sRGB
# The sRGB transfer function (IEC 61966-2-1): 12.92 x up to 0.0031308, then
# 1.055 x^(1/2.4) - 0.055. Values below 0 (a network's overshoot) stay on the linear
# segment and values above 1 on the power curve, so the encoding is monotone and its
# derivative finite everywhere (12.92 at and below the knee).
SRGB_KNEE = 0.0031308


def srgb_encode(rgb):
    """Linear RGB -> sRGB-coded values (display coding; differentiable, unclipped)."""
    power = 1.055 * jnp.power(jnp.maximum(rgb, SRGB_KNEE), 1.0 / 2.4) - 0.055
    return jnp.where(rgb <= SRGB_KNEE, 12.92 * rgb, power)


# ---------------------------------------------------------------- HDR
# The invertible tone map FSR 2 runs its history on (its ffx_fsr2_common.h ``Tonemap`` /
# ``InverseTonemap``): ``c / (1 + max(r, g, b))`` maps linear HDR [0, inf) into [0, 1)
# keeping hue; the inverse divides by ``1 - max``, clamped at ``TONEMAP_EPSILON`` (FSR 2's
# ``FSR2_TONEMAP_EPSILON``, 1/65503) so an output at or above 1 maps to a finite
# radiance, at most 65503, the largest float16 (the datasets' colour storage).
TONEMAP_EPSILON = 1.0 / 65503.0


def _max_rgb(x):
    return jnp.max(x, axis=-1, keepdims=True)


def tonemap(rgb):
    """Linear HDR RGB (>= 0) -> [0, 1): ``rgb / (1 + max(0, r, g, b))``."""
    return rgb / (1.0 + jnp.maximum(_max_rgb(rgb), 0.0))


def inverse_tonemap(t):
    """The inverse of ``tonemap``: ``t / max(epsilon, 1 - max(r, g, b))``."""
    return t / jnp.maximum(1.0 - _max_rgb(t), TONEMAP_EPSILON)


def exposure_scale(exposure, like):
    """``exposure [B]`` shaped to multiply images ``like [B,...]``."""
    return jnp.asarray(exposure, like.dtype).reshape(exposure.shape + (1,) * (like.ndim - 1))


def display(rgb, exposure):
    """What a viewer of HDR frames sees, and what jtus's losses and metrics compare:
    the tone-mapped pre-exposed colour ``tonemap(exposure * rgb)`` in [0, 1); ``rgb``
    itself when ``exposure`` is None (LDR data, already display-referred)."""
    if exposure is None:
        return rgb
    return tonemap(rgb * exposure_scale(exposure, rgb))
