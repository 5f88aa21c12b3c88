"""PSNR and SSIM against scikit-image."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from jtus import metrics


def _structured(h=40, w=52):
    yy, xx = np.mgrid[0:h, 0:w] / 8.0
    a = np.stack([np.sin(xx) * 0.5 + 0.5, (np.floor(xx) + np.floor(yy)) % 2,
                  np.clip(yy / 5, 0, 1)], -1)
    b = np.clip(a + 0.05 * np.cos(3 * xx + yy)[..., None], 0, 1)
    return a, b


@pytest.mark.parametrize("kind", ["random", "structured", "identical"])
def test_ssim_and_psnr_match_skimage(rng, kind):
    if kind == "random":
        a, b = rng.uniform(size=(2, 37, 45, 3))
    elif kind == "structured":
        a, b = _structured()
    else:
        a = rng.uniform(size=(30, 30, 3))
        b = a.copy()
    ours = float(jax.jit(metrics.ssim)(jnp.asarray(a[None], jnp.float32),
                                      jnp.asarray(b[None], jnp.float32))[0])
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False, data_range=1, channel_axis=-1)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-6)
    if kind != "identical":
        got = float(metrics.psnr(jnp.asarray(a[None]), jnp.asarray(b[None]))[0])
        np.testing.assert_allclose(got, peak_signal_noise_ratio(a, b, data_range=1), rtol=1e-5)


def test_ssim_map_matches_skimage_interior(x64, rng):
    a, b = rng.uniform(size=(2, 24, 26, 1))
    _, full = structural_similarity(a[..., 0], b[..., 0], gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1, full=True)
    ours = np.asarray(metrics.ssim_map(jnp.asarray(a[None]), jnp.asarray(b[None])))[0, ..., 0]
    np.testing.assert_allclose(ours, full[5:-5, 5:-5], rtol=0, atol=1e-12)


def test_ssim_rejects_small_or_mismatched():
    with pytest.raises(ValueError, match=r"11 pixels on each side, got \(8, 20\)$"):
        metrics.ssim(jnp.zeros((1, 8, 20, 3)), jnp.zeros((1, 8, 20, 3)))
    with pytest.raises(ValueError, match=r"got \(20, 10\)$"):
        metrics.ssim(jnp.zeros((1, 20, 10, 3)), jnp.zeros((1, 20, 10, 3)))
    # the smallest image that has one valid window: 11x11 gives a 1x1 map
    assert metrics.ssim_map(jnp.ones((1, 11, 11, 3)), jnp.ones((1, 11, 11, 3))).shape == (
        1, 1, 1, 3)
    with pytest.raises(ValueError, match="one shape"):
        metrics.ssim(jnp.zeros((1, 20, 20, 3)), jnp.zeros((1, 20, 21, 3)))


def test_ssim_keeps_float32_when_float64_is_enabled():
    """The filter taps take the images' dtype: float32 images give a float32 map even
    with float64 enabled (taps left in float64 would promote the whole map)."""
    x = np.random.default_rng(0).random((1, 16, 16, 3), np.float32)
    with jax.enable_x64(True):
        m = metrics.ssim_map(jnp.asarray(x), jnp.asarray(x[:, ::-1]))
        assert m.dtype == jnp.float32
        assert metrics.ssim_map(jnp.asarray(x, jnp.float64),
                                jnp.asarray(x[:, ::-1], jnp.float64)).dtype == jnp.float64
