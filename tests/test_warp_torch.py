"""Warps and up-sampling against PyTorch (grid_sample, interpolate, PixelShuffle)."""

import jax.numpy as jnp
import numpy as np
import pytest
import torch

from jtus import sampling
from tests import seqdata, torch_ref


def _grids(rng, b, h, w, ho, wo, dtype):
    """Random normalized grids mixing points outside the image, exactly on pixel
    centres and exactly on pixel edges (align_corners=False)."""
    g = rng.uniform(-1.4, 1.4, size=(b, ho, wo, 2))
    size = np.array([w, h])
    centres = (2 * (rng.integers(0, size, size=(b, ho, wo, 2)) + 0.5)) / size - 1
    edges = 2 * rng.integers(0, size + 1, size=(b, ho, wo, 2)) / size - 1
    pick = rng.integers(0, 3, size=(b, ho, wo, 1))
    g = np.where(pick == 1, centres, np.where(pick == 2, edges, g))
    return g.astype(dtype)


@pytest.mark.parametrize("method,mode", [("bilinear", "bilinear"), ("bicubic", "bicubic")])
@pytest.mark.parametrize("align_corners", [False, True])
def test_grid_sample_float32(rng, method, mode, align_corners):
    img = rng.normal(size=(2, 13, 17, 3)).astype(np.float32)
    grid = _grids(rng, 2, 13, 17, 11, 19, np.float32)
    ours = np.asarray(sampling.grid_sample(jnp.asarray(img), jnp.asarray(grid), method=method,
                                           align_corners=align_corners))
    ref = torch_ref.grid_sample(img, grid, mode, align_corners)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize("method,mode", [("bilinear", "bilinear"), ("bicubic", "bicubic")])
def test_grid_sample_float64(x64, rng, method, mode):
    img = rng.normal(size=(2, 13, 17, 3))
    grid = _grids(rng, 2, 13, 17, 11, 19, np.float64)
    ours = np.asarray(sampling.grid_sample(jnp.asarray(img), jnp.asarray(grid), method=method))
    assert ours.dtype == np.float64
    ref = torch_ref.grid_sample(img, grid, mode)
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10)


def test_grid_sample_defaults_and_keys_parameter(x64, rng):
    """Called with the image and grid alone, ``grid_sample`` is torch's default
    (bilinear, ``align_corners=False``); its ``a`` reaches the cubic kernel: bicubic with
    a=-0.5 is Catmull-Rom, and differs from the default a=-0.75."""
    img = jnp.asarray(rng.normal(size=(2, 13, 17, 3)))
    grid = jnp.asarray(_grids(rng, 2, 13, 17, 11, 19, np.float64))
    np.testing.assert_allclose(np.asarray(sampling.grid_sample(img, grid)),
                               torch_ref.grid_sample(np.asarray(img), np.asarray(grid),
                                                     "bilinear"), rtol=0, atol=1e-10)
    cr = np.asarray(sampling.grid_sample(img, grid, "bicubic", a=-0.5))
    np.testing.assert_array_equal(cr, sampling.grid_sample(img, grid, "catmull_rom"))
    assert np.abs(cr - np.asarray(sampling.grid_sample(img, grid, "bicubic"))).max() > 1e-2


@pytest.mark.parametrize("factor", [2, 4])
def test_upsample_bilinear_matches_interpolate(rng, factor):
    x = rng.normal(size=(2, 9, 7, 2)).astype(np.float32)
    ours = np.asarray(sampling.upsample(jnp.asarray(x), factor))
    np.testing.assert_allclose(ours, torch_ref.interpolate_bilinear(x, factor), rtol=0, atol=1e-6)


def test_upsample_bilinear_matches_interpolate_float64(x64, rng):
    x = rng.normal(size=(1, 6, 5, 2))
    ours = np.asarray(sampling.upsample(jnp.asarray(x), 4))
    np.testing.assert_allclose(ours, torch_ref.interpolate_bilinear(x, 4), rtol=0, atol=1e-12)


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_upsample_bicubic_matches_interpolate_float64(x64, rng, factor):
    """The non-bilinear methods sample the LR image at the HR centres: bicubic equals
    ``F.interpolate(mode="bicubic")`` (a=-0.75, borders clamped); a float32 image stays
    float32 with 64-bit types on."""
    x = rng.normal(size=(2, 6, 5, 2))
    ours = np.asarray(sampling.upsample(jnp.asarray(x), factor, method="bicubic"))
    np.testing.assert_allclose(ours, torch_ref.interpolate_bicubic(x, factor), rtol=0,
                               atol=1e-12)
    x32 = jnp.asarray(x, jnp.float32)
    assert sampling.upsample(x32, factor, method="bicubic").dtype == jnp.float32


@pytest.mark.parametrize("method,mode", [("bicubic", "bicubic"), ("nearest", "nearest")])
@pytest.mark.parametrize("factor", [2, 3, 4])
def test_jau_non_bilinear_methods_equal_grid_sample_float64(x64, rng, method, mode, factor):
    """JAU with a sampling method other than bilinear reads the LR image at each HR
    centre minus the jitter plus half a pixel (thesis sec. 4.1.1), in the image's
    precision: ``F.grid_sample`` (border padding) at those positions, written here in
    normalized coordinates. Factor 3's positions are not dyadic, so positions computed
    in float32 would miss by about 1e-7 of a pixel."""
    b, h, w = 2, 5, 6
    x = rng.normal(size=(b, h, w, 2))
    jit = rng.uniform(0, 1, size=(b, 2))
    ours = np.asarray(sampling.jitter_aligned_upsample(jnp.asarray(x), jnp.asarray(jit),
                                                       factor, method=method))
    assert ours.dtype == np.float64
    grid = 2 * seqdata.jau_positions(jit, h, w, factor) / np.array([w, h]) - 1
    # nearest: a position exactly on a pixel edge rounds differently; none is here
    # (random jitter), and both then take the pixel containing the point
    np.testing.assert_allclose(ours, torch_ref.grid_sample(x, grid, mode), rtol=0, atol=1e-12)


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_pixel_shuffle_exact(rng, factor):
    x = rng.normal(size=(2, 5, 6, 2 * factor * factor)).astype(np.float32)
    ours = np.asarray(sampling.pixel_shuffle(jnp.asarray(x), factor))
    ref = torch_ref.to_nhwc(torch.nn.PixelShuffle(factor)(torch_ref.to_nchw(x)))
    np.testing.assert_array_equal(ours, ref)
    back = np.asarray(sampling.pixel_unshuffle(jnp.asarray(ours), factor))
    ref_back = torch_ref.to_nhwc(torch.nn.PixelUnshuffle(factor)(torch_ref.to_nchw(ref)))
    np.testing.assert_array_equal(back, ref_back)
    np.testing.assert_array_equal(back, x)
