"""Properties of the hand-written warps: exactness, partition of unity, polynomial
reproduction, the 9- and 5-fetch kernels, and gradients (float64 check_grads)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from jtus import sampling

ALL = sampling.METHODS
CUBIC = ("bicubic", "catmull_rom", "bicubic9", "bicubic5")


def _image(seed, b=1, h=9, w=11, c=3, dtype=np.float32):
    return jnp.asarray(np.random.default_rng(seed).normal(size=(b, h, w, c)).astype(dtype))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), method=st.sampled_from(ALL),
       a=st.sampled_from([-0.5, -0.75]))
def test_zero_motion_is_identity(seed, method, a):
    img = _image(seed)
    xy = sampling.pixel_grid(1, 9, 11)
    np.testing.assert_array_equal(np.asarray(sampling.sample(img, xy, method, a=a)), img)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), method=st.sampled_from(ALL),
       dx=st.integers(-2, 2), dy=st.integers(-2, 2))
def test_integer_shift_exact_away_from_borders(seed, method, dx, dy):
    img = _image(seed, h=12, w=12)
    xy = sampling.pixel_grid(1, 12, 12) + jnp.asarray([dx, dy], jnp.float32)
    out = np.asarray(sampling.sample(img, xy, method))
    # Interior: output pixel (i, j) whose taps (up to 2 away) stay in the image.
    inner = slice(4, 8)
    np.testing.assert_array_equal(out[:, inner, inner],
                                  np.asarray(img)[:, 4 + dy:8 + dy, 4 + dx:8 + dx])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), method=st.sampled_from(ALL),
       value=st.floats(-4, 4), a=st.sampled_from([-0.5, -0.75]))
def test_constant_image_stays_constant(seed, method, value, a):
    with jax.enable_x64(True):
        img = jnp.full((1, 7, 6, 2), value, jnp.float64)
        xy = jnp.asarray(np.random.default_rng(seed).uniform(-5, 12, size=(1, 8, 8, 2)))
        out = np.asarray(sampling.sample(img, xy, method, a=a))
    np.testing.assert_allclose(out, value, rtol=0, atol=1e-13 * max(1.0, abs(value)))


def _quadratic_image(h=16, w=16):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)  # index coordinates
    return 0.3 * xx**2 - 1.1 * xx * yy + 0.7 * yy**2 + 2 * xx - yy + 0.5


@pytest.mark.parametrize("method", ["catmull_rom", "bicubic9"])
def test_catmull_rom_reproduces_quadratics(x64, method):
    q = _quadratic_image()
    xy = np.random.default_rng(3).uniform(4, 12, size=(1, 20, 20, 2))
    out = np.asarray(sampling.sample(jnp.asarray(q[None, :, :, None]), jnp.asarray(xy),
                                     method, a=-0.5))[0, ..., 0]
    u, v = xy[0, ..., 0] - 0.5, xy[0, ..., 1] - 0.5
    exact = 0.3 * u**2 - 1.1 * u * v + 0.7 * v**2 + 2 * u - v + 0.5
    np.testing.assert_allclose(out, exact, rtol=0, atol=1e-11)


def test_keys_075_does_not_reproduce_quadratics(x64):
    q = _quadratic_image()
    xy = np.random.default_rng(3).uniform(4, 12, size=(1, 20, 20, 2))
    out = np.asarray(sampling.sample(jnp.asarray(q[None, :, :, None]), jnp.asarray(xy),
                                     "bicubic", a=-0.75))[0, ..., 0]
    u, v = xy[0, ..., 0] - 0.5, xy[0, ..., 1] - 0.5
    exact = 0.3 * u**2 - 1.1 * u * v + 0.7 * v**2 + 2 * u - v + 0.5
    assert np.abs(out - exact).max() > 1e-2


@pytest.mark.parametrize("a", [-0.5, -0.75])
def test_bicubic9_equals_16_taps(x64, a):
    img = jnp.asarray(np.random.default_rng(0).uniform(size=(2, 10, 13, 3)))
    xy = jnp.asarray(np.random.default_rng(1).uniform(-3, 16, size=(2, 15, 17, 2)))
    ref = sampling.sample(img, xy, "bicubic", a=a)
    np.testing.assert_allclose(sampling.sample(img, xy, "bicubic9", a=a), ref, rtol=0, atol=1e-14)
    img32, xy32 = img.astype(jnp.float32), xy.astype(jnp.float32)
    np.testing.assert_allclose(sampling.sample(img32, xy32, "bicubic9", a=a),
                               sampling.sample(img32, xy32, "bicubic", a=a), rtol=0, atol=2e-6)


@pytest.mark.parametrize("a,bound", [(-0.5, 0.016), (-0.75, 0.036)])
def test_bicubic5_error_is_bounded(x64, a, bound):
    """The 5 fetches drop the 4 corner weights, each a product of two negative
    outer-lobe weights, so they sum to at most (2 * |a| / 8)^2 (at t = 1/2);
    after renormalization the error on a [0,1] image stays below about that."""
    img = jnp.asarray(np.random.default_rng(0).uniform(size=(1, 32, 32, 3)))
    xy = jnp.asarray(np.random.default_rng(1).uniform(2, 30, size=(1, 64, 64, 2)))
    err = np.abs(np.asarray(sampling.sample(img, xy, "bicubic5", a=a)
                            - sampling.sample(img, xy, "bicubic", a=a)))
    assert err.max() <= bound
    assert err.max() > bound / 4  # the approximation does differ
    # At pixel centres (t = 0) the outer weights vanish and it is exact.
    centres = sampling.pixel_grid(1, 32, 32, jnp.float64)
    np.testing.assert_array_equal(sampling.sample(img, centres, "bicubic5", a=a), img)


def _interior_coords(seed, shape):
    """Coordinates whose fractional parts stay in [0.1, 0.9]: away from tap boundaries."""
    rng = np.random.default_rng(seed)
    base = rng.integers(1, 6, size=shape)
    return jnp.asarray(base + 0.5 + rng.uniform(0.1, 0.9, size=shape))


@pytest.mark.parametrize("method", ALL[1:])  # nearest is piecewise constant in xy
def test_check_grads_float64(x64, method):
    img = jnp.asarray(np.random.default_rng(0).normal(size=(1, 7, 8, 2)))
    xy = _interior_coords(1, (1, 3, 4, 2))
    check_grads(lambda im: sampling.sample(im, xy, method), (img,), order=2, modes=("fwd", "rev"))
    check_grads(lambda p: sampling.sample(img, p, method), (xy,), order=2, modes=("fwd", "rev"),
                eps=1e-6)


@pytest.mark.parametrize("method", ALL[1:])
def test_coordinate_gradient_nonzero_at_pixel_centres(x64, method):
    img = jnp.asarray(np.random.default_rng(0).normal(size=(1, 7, 8, 1)))
    xy = sampling.pixel_grid(1, 7, 8, jnp.float64)
    g = jax.grad(lambda p: sampling.sample(img, p, method)[0, 2:5, 2:6].sum())(xy)
    g = np.asarray(g)[0, 2:5, 2:6]
    assert np.all(np.abs(g).sum(-1) > 1e-3)


def test_nearest_picks_containing_pixel():
    img = jnp.arange(12, dtype=jnp.float32).reshape(1, 3, 4, 1)
    xy = jnp.asarray([[[[0.0, 0.0], [0.99, 2.99], [3.5, 1.0], [9.0, -4.0]]]], jnp.float32)
    out = np.asarray(sampling.sample(img, xy, "nearest"))[0, 0, :, 0]
    np.testing.assert_array_equal(out, [0, 8, 7, 3])


def test_inside_mask():
    xy = jnp.asarray([[[[0.0, 0.0], [4.0, 3.0], [-0.01, 1.0], [2.0, 3.01]]]])
    for method in sampling.METHODS:  # each method's plan carries the mask
        _, mask = sampling.sample(jnp.zeros((1, 3, 4, 1)), xy, method, return_mask=True)
        assert mask.shape == (1, 1, 4, 1) and mask.dtype == bool, method
        np.testing.assert_array_equal(np.asarray(mask)[0, 0, :, 0], [True, True, False, False])


def test_bad_input_errors():
    img = jnp.zeros((1, 4, 4, 3))
    with pytest.raises(ValueError, match="method"):
        sampling.sample(img, jnp.zeros((1, 2, 2, 2)), "lanczos")
    with pytest.raises(ValueError, match="xy"):
        sampling.sample(img, jnp.zeros((1, 2, 2, 3)))
    with pytest.raises(ValueError, match=r"image: expected \[B,H,W,C\], got shape \(4, 4, 3\)"):
        sampling.sample(jnp.zeros((4, 4, 3)), jnp.zeros((1, 2, 2, 2)))
    with pytest.raises(ValueError, match=r"xy: expected \[B,Ho,Wo,2\] with B=2, got shape "
                                         r"\(1, 2, 2, 2\)"):
        sampling.sample(jnp.zeros((2, 4, 5, 3)), jnp.zeros((1, 2, 2, 2)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_broadcast_linear_weights_equal_one_minus_t_and_t_bit_for_bit(x64, dtype):
    from jtus.sampling.warp import _linear_weights

    t = np.random.default_rng(3).uniform(0, 1, size=(1000, 1)).astype(dtype)
    t[:3, 0] = [0.0, 0.5, np.nextafter(dtype(1), dtype(0))]
    got = np.asarray(_linear_weights(jnp.asarray(t)))
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, np.concatenate([1 - t, t], -1))


def test_separable_read_derivatives_equal_plain_autodiff(x64, rng):
    """The warps' custom derivative rule (one gather of all taps for the image, whose
    transpose is one scatter) gives plain autodiff's derivatives, image and weights,
    forward and reverse, with taps clamped at the borders."""
    from jtus.sampling.warp import _rows, _separable

    img = jnp.asarray(rng.normal(size=(2, 7, 9, 3)))
    iy0 = jnp.asarray(rng.integers(-3, 8, size=(2, 5, 6)), jnp.int32)
    ix0 = jnp.asarray(rng.integers(-3, 10, size=(2, 5, 6)), jnp.int32)
    wy, wx = (jnp.asarray(rng.normal(size=(2, 5, 6, 4))) for _ in range(2))
    ct = jnp.asarray(rng.normal(size=(2, 5, 6, 3)))
    ref, vjp_ref = jax.vjp(lambda a, b, c: _rows(a, iy0, ix0, b, c), img, wy, wx)
    out, vjp = jax.vjp(lambda a, b, c: _separable(a, iy0, ix0, b, c), img, wy, wx)
    np.testing.assert_array_equal(out, ref)
    for g, g_ref in zip(vjp(ct), vjp_ref(ct)):
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12)
    tangents = tuple(jnp.asarray(rng.normal(size=x.shape)) for x in (img, wy, wx))
    _, t = jax.jvp(lambda a, b, c: _separable(a, iy0, ix0, b, c), (img, wy, wx), tangents)
    _, t_ref = jax.jvp(lambda a, b, c: _rows(a, iy0, ix0, b, c), (img, wy, wx), tangents)
    np.testing.assert_allclose(t, t_ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", sampling.METHODS)
def test_edges_of_the_input_domain(method):
    """Integer coordinates and images are cast, not truncated: bilinear at the integer
    corner (2, 2) of a 4x4 ramp is the mean of its 4 neighbours (7.5), as at (2.0, 2.0);
    NaN coordinates give NaN with every method; coordinates far outside read the edge
    with a zero, finite gradient (no wrapped tap index)."""
    img = jnp.arange(16.0).reshape(1, 4, 4, 1)
    xy_int = jnp.array([[[[2, 2], [1, 3]]]])
    np.testing.assert_array_equal(sampling.sample(img, xy_int, method),
                                  sampling.sample(img, xy_int.astype(jnp.float32), method))
    if method == "bilinear":
        assert float(sampling.sample(img, xy_int, method)[0, 0, 0, 0]) == 7.5
    xy = jnp.array([[[[1.75, 1.5]]]])
    np.testing.assert_allclose(sampling.sample(img.astype(jnp.int32), xy, method),
                               sampling.sample(img, xy, method), rtol=1e-6)
    nan = sampling.sample(img, jnp.array([[[[jnp.nan, 1.5], [1.5, jnp.nan]]]]), method)
    assert np.all(np.isnan(np.asarray(nan)))
    for far in (3e9, -3e9):
        def read(x):
            return sampling.sample(img, jnp.stack([x, jnp.float32(1.5)])[None, None, None],
                                   method).sum()
        v, g = jax.value_and_grad(read)(jnp.float32(far))
        edge = img[0, 1:3, -1 if far > 0 else 0, 0]  # rows around y = 1.5 at the edge column
        assert float(edge.min()) - 1e-4 <= float(v) <= float(edge.max()) + 1e-4
        assert np.isfinite(float(g)) and float(g) == 0.0


def _bicubic5_reference(img, xy, a):
    """UE4's 5-fetch bicubic from its definition on the 16 taps: the Keys weights of the
    taps whose row and column are not both outer (the four corners dropped), clamped
    indices, divided by those weights' sum. numpy, float64, tap by tap; Keys (1981)
    eq. 15 written out here, not ``keys_weights``."""
    def keys(d):  # the kernel at distance d
        d = abs(d)
        if d <= 1:
            return (a + 2) * d ** 3 - (a + 3) * d ** 2 + 1
        return a * d ** 3 - 5 * a * d ** 2 + 8 * a * d - 4 * a if d < 2 else 0.0

    b, h, w, c = img.shape
    out = np.zeros(xy.shape[:-1] + (c,))
    for n, i, j in np.ndindex(*xy.shape[:-1]):
        x, y = xy[n, i, j] - 0.5
        ix0, iy0 = int(np.floor(x)), int(np.floor(y))
        wx = [keys(x - (ix0 - 1 + k)) for k in range(4)]
        wy = [keys(y - (iy0 - 1 + k)) for k in range(4)]
        num, den = 0.0, 0.0
        for ky in range(4):
            for kx in range(4):
                if kx in (0, 3) and ky in (0, 3):
                    continue
                wgt = float(wx[kx]) * float(wy[ky])
                row = min(max(iy0 - 1 + ky, 0), h - 1)
                col = min(max(ix0 - 1 + kx, 0), w - 1)
                num = num + wgt * img[n, row, col]
                den += wgt
        out[n, i, j] = num / den
    return out


@pytest.mark.parametrize("a", [-0.5, -0.75])
def test_bicubic5_against_its_definition(x64, a):
    """``bicubic5`` (5 bilinear fetches) equals the 16-tap Keys kernel without its four
    corner taps, renormalized (numpy, per tap), in float64 across the borders: to 3e-15
    (measured 8.9e-16 at a=-0.5, 1.4e-15 at a=-0.75)."""
    rng = np.random.default_rng(5)
    img = rng.uniform(size=(2, 6, 7, 2))
    xy = rng.uniform(-1.5, 8.5, size=(2, 5, 4, 2))
    got = np.asarray(sampling.sample(jnp.asarray(img), jnp.asarray(xy), "bicubic5", a=a))
    np.testing.assert_allclose(got, _bicubic5_reference(img, xy, a), rtol=0, atol=3e-15)


def test_float32_warps_are_the_same_with_64_bit_types_on(rng):
    """Every method reads a float32 image at float32 coordinates in float32, whether or
    not 64-bit types are on: the same bits (training runs in float32 beside float64
    references)."""
    img = jnp.asarray(rng.normal(size=(2, 9, 11, 3)), jnp.float32)
    xy = jnp.asarray(rng.uniform(-2, 12, size=(2, 7, 8, 2)), jnp.float32)
    off = [sampling.sample(img, xy, m) for m in sampling.METHODS]
    with jax.enable_x64(True):
        on = [sampling.sample(img, xy, m) for m in sampling.METHODS]
    for m, x, y in zip(sampling.METHODS, on, off):
        assert x.dtype == jnp.float32, m
        np.testing.assert_array_equal(x, y, err_msg=m)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_pixel_grid_centres_in_the_asked_type(x64, dtype):
    """``pixel_grid`` is the pixel centres (x, y) = (j + 0.5, i + 0.5) in the type asked
    for, float32 too with 64-bit types on (as the float32 warps read it)."""
    g = sampling.pixel_grid(2, 3, 4, dtype)
    assert g.dtype == dtype and g.shape == (2, 3, 4, 2)
    i, j = np.mgrid[0:3, 0:4]
    np.testing.assert_array_equal(g, np.broadcast_to(np.stack([j + 0.5, i + 0.5], -1),
                                                     (2, 3, 4, 2)))


def test_warp_read_checks_its_method_and_plan(rng):
    """``warp_read`` reads bilinearly by default (the plan's default), as ``sample``; a
    method it does not know, or a plan made for a method of the other kind (per-axis
    taps against bilinear fetches), is an error naming the argument."""
    img = jnp.asarray(rng.normal(size=(1, 5, 6, 2)), jnp.float32)
    xy = jnp.asarray(rng.uniform(0, 6, size=(1, 3, 4, 2)), jnp.float32)
    np.testing.assert_array_equal(sampling.warp_read(img, sampling.warp_plan(xy, 5, 6)),
                                  sampling.sample(img, xy))
    with pytest.raises(ValueError, match="method: expected one of"):
        sampling.warp_read(img, sampling.warp_plan(xy, 5, 6), "lanczos")
    with pytest.raises(ValueError, match=re.escape(
            "p: a WarpPlan made for another method than 'bicubic' (made with bicubic9 or "
            "bicubic5)")):
        sampling.warp_read(img, sampling.warp_plan(xy, 5, 6, "bicubic9"), "bicubic")
    with pytest.raises(ValueError, match=re.escape(
            "p: a WarpPlan made for another method than 'bicubic5' (made with a separable "
            "one)")):
        sampling.warp_read(img, sampling.warp_plan(xy, 5, 6), "bicubic5")


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_float64_coordinates_keep_their_precision_on_a_float32_image(x64, method):
    """A float32 image read at float64 coordinates is read at those coordinates, not at
    their float32 roundings: at x near 4000 a float32 step is 2.4e-4 pixels, which on a
    random image moves a value by about 1e-4 (measured 9.1e-5 bilinear, 1.0e-4 bicubic);
    kept in float64, the read matches the float64 image's to float32 rounding (bound
    1.5e-6; measured 6.7e-8 bilinear, 6.9e-7 bicubic)."""
    rng = np.random.default_rng(7)
    img = rng.uniform(size=(1, 3, 4096, 1))
    x = 4000 + rng.uniform(0, 90, size=(1, 1, 64))
    xy = jnp.asarray(np.stack([x, np.full_like(x, 1.5)], -1))
    assert xy.dtype == jnp.float64
    got = sampling.sample(jnp.asarray(img, jnp.float32), xy, method)
    assert got.dtype == jnp.float32
    ref = np.asarray(sampling.sample(jnp.asarray(img), xy, method))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1.5e-6)


@pytest.mark.parametrize("method", sampling.METHODS)
def test_a_nan_coordinate_spoils_only_its_own_read(method):
    """A NaN coordinate gives NaN at its own output pixel and nowhere else."""
    img = jnp.arange(16.0).reshape(1, 4, 4, 1)
    xy = jnp.array([[[[1.5, 1.5], [jnp.nan, 2.0], [2.5, 0.5]]]])
    out = np.asarray(sampling.sample(img, xy, method))[0, 0, :, 0]
    np.testing.assert_array_equal(np.isnan(out), [False, True, False])


@pytest.mark.parametrize("wide", [False, True])
def test_an_image_is_read_in_its_own_float_type_and_integers_as_float32(wide):
    """``sample`` reads a floating image in its own type (a half-precision history stays
    half) and an integer image (8-bit colour) as float32, with 64-bit types on or off:
    the values are those of the float32 image's read."""
    with jax.enable_x64(wide):
        rng = np.random.default_rng(3)
        img = rng.integers(0, 256, size=(1, 5, 6, 3)).astype(np.uint8)
        xy = jnp.asarray(rng.uniform(0, 6, size=(1, 4, 4, 2)), jnp.float32)
        for method in ("nearest", "bilinear", "bicubic"):
            got = sampling.sample(jnp.asarray(img), xy, method)
            assert got.dtype == jnp.float32, method
            np.testing.assert_array_equal(
                np.asarray(got), np.asarray(sampling.sample(jnp.asarray(img, jnp.float32),
                                                            xy, method)))
            half = sampling.sample(jnp.asarray(img, jnp.float16), xy, method)
            assert half.dtype == jnp.float16, method


@pytest.mark.parametrize("method", sampling.METHODS)
def test_offset_plan_reads_where_warp_plan_reads(method):
    """``offset_plan(index, d)`` reads what ``warp_plan(index + 0.5 + d)`` reads where
    that float32 sum is exact (small images, displacements on a 1/64 grid, some past
    the borders and some exactly on them), with the same ``inside``."""
    rng = np.random.default_rng(11)
    img = jnp.asarray(rng.normal(size=(2, 7, 9, 3)).astype(np.float32))
    index = jnp.asarray(rng.integers(0, 9, size=(2, 5, 6, 2)), jnp.int32)
    d = rng.integers(-12 * 64, 12 * 64, size=(2, 5, 6, 2)) / 64.0
    d[0, 0, 0] = -np.asarray(index[0, 0, 0]) - 0.5           # on the left/top border
    d[1, 0, 0] = np.array([9.0, 7.0]) - np.asarray(index[1, 0, 0]) - 0.5  # right/bottom
    d = jnp.asarray(d, jnp.float32)
    p = sampling.offset_plan(index, d, 7, 9, method)
    q = sampling.warp_plan(index + 0.5 + d, 7, 9, method)
    np.testing.assert_array_equal(np.asarray(p.inside), np.asarray(q.inside))
    np.testing.assert_allclose(np.asarray(sampling.warp_read(img, p, method)),
                               np.asarray(sampling.warp_read(img, q, method)), atol=1e-6)


@pytest.mark.parametrize("method", ["bilinear", "bicubic", "catmull_rom"])
def test_reproject_plan_reads_at_the_unrounded_position(x64, method):
    """At 1920 pixels wide a float32 pixel centre plus a displacement rounds to 1.2e-4
    pixels; ``reproject_plan`` keeps the two apart, so its float32 read of a random
    image matches the float64 read at the float32 displacement to float32 rounding
    (bound 2e-6; measured 1.2e-7 bilinear, 1.2e-6 bicubic), where the summed
    coordinates miss by 5.1e-5-8.0e-5 (asserted above 2e-5, so the comparison can tell
    the two apart)."""
    rng = np.random.default_rng(5)
    f, h, w = 4, 2, 480
    img = rng.uniform(size=(1, f * h, f * w, 1))
    motion = rng.normal(0.0, 1.5, size=(1, h, w, 2)).astype(np.float32)
    d = f * np.asarray(sampling.upsample(jnp.asarray(motion), f), np.float64)
    exact = sampling.sample(jnp.asarray(img), sampling.pixel_grid(1, f * h, f * w,
                                                                  jnp.float64) + d, method)
    img32 = jnp.asarray(img, jnp.float32)
    got = sampling.warp_read(img32, sampling.reproject_plan(jnp.asarray(motion), f, method),
                             method)
    summed = sampling.sample(img32, sampling.reproject_coords(jnp.asarray(motion), f), method)
    assert float(jnp.abs(summed - exact).max()) > 2e-5
    np.testing.assert_allclose(np.asarray(got), np.asarray(exact), rtol=0, atol=2e-6)
