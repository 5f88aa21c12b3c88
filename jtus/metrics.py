"""Image-quality metrics, jit-able so they run inside evaluation rollouts.

Images are ``[B,H,W,C]`` with data range 1; every metric returns one value per batch
element, ``[B]``.

SSIM follows ``skimage.metrics.structural_similarity(gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)``: an 11-tap
Gaussian window (sigma 1.5, truncated at 3.5 sigma), C1 = 0.01^2, C2 = 0.03^2, the
per-channel maps averaged. Borders: only windows that lie wholly inside the image
are used (a "valid" filter). scikit-image filters with reflection and then discards
the 5-pixel border before averaging, so the two means cover the same pixels and agree.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

SSIM_SIGMA = 1.5
SSIM_RADIUS = int(3.5 * SSIM_SIGMA + 0.5)  # scikit-image's truncate=3.5: 11 taps
C1, C2 = 0.01**2, 0.03**2


def _gaussian_taps():
    x = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return g / g.sum()


def _filter_valid(x, taps):
    """Separable 'valid' filtering along H then W of ``[B,H,W,C]``."""
    n = len(taps)
    h, w = x.shape[1] - n + 1, x.shape[2] - n + 1
    t = jnp.asarray(taps, x.dtype)
    y = sum(t[k] * x[:, k:k + h] for k in range(n))
    return sum(t[k] * y[:, :, k:k + w] for k in range(n))


def ssim_map(a, b):
    """The SSIM map ``[B,H-10,W-10,C]`` (valid windows only)."""
    if a.shape != b.shape or a.ndim != 4:
        raise ValueError(f"ssim: expected two [B,H,W,C] arrays of one shape, got {a.shape} "
                         f"and {b.shape}")
    if min(a.shape[1:3]) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"ssim: images must be at least {2 * SSIM_RADIUS + 1} pixels on each "
                         f"side, got {a.shape[1:3]}")
    taps = _gaussian_taps()
    ux, uy = _filter_valid(a, taps), _filter_valid(b, taps)
    vx = _filter_valid(a * a, taps) - ux * ux
    vy = _filter_valid(b * b, taps) - uy * uy
    vxy = _filter_valid(a * b, taps) - ux * uy
    return ((2 * ux * uy + C1) * (2 * vxy + C2)) / ((ux * ux + uy * uy + C1) * (vx + vy + C2))


def ssim(a, b):
    return ssim_map(a, b).mean(axis=(1, 2, 3))


def mse(a, b):
    return jnp.mean(jnp.square(a - b), axis=(1, 2, 3))


def psnr(a, b):
    """Peak signal-to-noise ratio in dB for data range 1."""
    return -10.0 * jnp.log10(mse(a, b))


__all__ = ["C1", "C2", "mse", "psnr", "ssim", "ssim_map"]
