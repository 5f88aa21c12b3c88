"""Zero-up-sampling, jitter-aligned up-sampling, motion dilation, jitter sequences, colour."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import sampling
from jtus.sampling import jitter
from tests import seqdata


@pytest.mark.parametrize("factor", [2, 4])
def test_zero_upsample_places_samples_under_jitter(rng, factor):
    x = rng.uniform(0.1, 1, size=(2, 3, 5, 4)).astype(np.float32)
    jitter = np.array([[0.1, 0.9], [0.6, 0.3]], np.float32)
    out = np.asarray(sampling.zero_upsample(jnp.asarray(x), jnp.asarray(jitter), factor))
    assert out.shape == (2, 3 * factor, 5 * factor, 4)
    for b in range(2):
        ox, oy = (jitter[b] * factor).astype(int)
        np.testing.assert_array_equal(out[b, oy::factor, ox::factor], x[b])
        mask = np.ones(out.shape[1:3], bool)
        mask[oy::factor, ox::factor] = False
        assert np.all(out[b][mask] == 0)


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
@pytest.mark.parametrize("factor", [2, 4])
def test_jau_reproduces_samples_at_their_positions(rng, method, factor):
    """An HR pixel whose centre is the sample position gets the LR sample exactly."""
    x = rng.normal(size=(1, 4, 6, 3)).astype(np.float32)
    cell = np.array([1, factor - 1])
    jitter = ((cell + 0.5) / factor)[None].astype(np.float32)
    out = np.asarray(sampling.jitter_aligned_upsample(jnp.asarray(x), jnp.asarray(jitter),
                                                      factor, method))
    np.testing.assert_allclose(out[0, cell[1]::factor, cell[0]::factor], x[0], atol=1e-6)


def test_jau_of_linear_ramp_is_the_ramp(x64):
    """A linear function sampled at jittered positions is rebuilt exactly by bilinear JAU
    away from the borders (it would be shifted by the jitter without the alignment)."""
    f, jit = 4, np.array([[0.3, 0.8]])
    h, w = 6, 7
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ramp = lambda x, y: 0.4 * x - 0.25 * y + 1.0  # noqa: E731
    lr = ramp(xx + jit[0, 0], yy + jit[0, 1])[None, :, :, None]  # value at the sample position
    out = np.asarray(sampling.jitter_aligned_upsample(jnp.asarray(lr), jnp.asarray(jit), f))
    Y, X = np.mgrid[0:h * f, 0:w * f]
    exact = ramp((X + 0.5) / f, (Y + 0.5) / f)
    np.testing.assert_allclose(out[0, f:-f, f:-f, 0], exact[f:-f, f:-f], atol=1e-12)


def test_dilate_motion_takes_nearest_neighbour():
    depth = np.full((1, 4, 4, 1), 0.9, np.float32)
    depth[0, 1, 2] = 0.1  # a near pixel
    motion = np.zeros((1, 4, 4, 2), np.float32)
    motion[0, 1, 2] = [3.0, -2.0]
    out = np.asarray(sampling.dilate_motion(jnp.asarray(motion), jnp.asarray(depth)))
    expect = np.zeros_like(motion)
    expect[0, 0:3, 1:4] = [3.0, -2.0]
    np.testing.assert_array_equal(out, expect)


def test_dilate_motion_ties_keep_centre(rng):
    motion = rng.normal(size=(1, 5, 5, 2)).astype(np.float32)
    depth = np.full((1, 5, 5, 1), 0.5, np.float32)
    out = sampling.dilate_motion(jnp.asarray(motion), jnp.asarray(depth))
    np.testing.assert_array_equal(out, motion)


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_dense_bilinear_equals_sampling(x64, rng, factor):
    """The gather-free bilinear up-sampling and JAU equal sampling the LR image at
    the HR positions (per-tap border clamping included), in values and in
    gradients with respect to the image and the jitter, to float64 rounding. The
    gradients are taken at jitters off the kinks of the bilinear weights: where a
    position lands exactly on an LR pixel centre (jitter 0.5 at factor 3) either
    one-sided derivative is right, and which one a program takes depends on how XLA
    rounds the position (eager and jitted differ there; 1e-9 to either side they agree)."""
    from jtus.sampling.upsample import hr_to_lr_coords

    x = jnp.asarray(rng.uniform(size=(3, 5, 7, 2)))
    jit = jnp.asarray([[0.0, 0.0], [0.999, 0.5], [0.3, 1.0]])
    b, h, w, _ = x.shape
    grid = hr_to_lr_coords(b, h, w, factor, x.dtype)

    def ref_jau(x, j):
        return sampling.sample(x, grid - j[:, None, None, :] + 0.5, "bilinear")

    np.testing.assert_allclose(sampling.upsample(x, factor),
                               sampling.sample(x, grid, "bilinear"), rtol=0, atol=1e-14)
    np.testing.assert_allclose(sampling.jitter_aligned_upsample(x, jit, factor),
                               ref_jau(x, jit), rtol=0, atol=1e-14)
    cot = jnp.asarray(rng.normal(size=(b, h * factor, w * factor, 2)))
    off_kinks = jnp.asarray([[0.01, 0.02], [0.999, 0.47], [0.3, 0.98]])
    # jitted: op-by-op float64 gradients of the warp took most of this test's time
    got = jax.jit(jax.grad(lambda x, j: jnp.sum(sampling.jitter_aligned_upsample(x, j, factor)
                                                * cot), argnums=(0, 1)))(x, off_kinks)
    want = jax.jit(jax.grad(lambda x, j: jnp.sum(ref_jau(x, j) * cot), argnums=(0, 1)))(
        x, off_kinks)
    for g, r in zip(got, want):
        np.testing.assert_allclose(g, r, rtol=0, atol=1e-12)


@pytest.mark.parametrize("mode", ["edge", "constant", "reflect"])
@pytest.mark.parametrize("size", [3, 5])
def test_neighbourhood_against_numpy(rng, size, mode):
    """Raster order of each pixel's size x size window, padded by numpy's ``mode``."""
    x = rng.normal(size=(2, 5, 6, 3)).astype(np.float32)
    r = size // 2
    p = np.pad(x, ((0, 0), (r, r), (r, r), (0, 0)), mode=mode)
    want = np.stack([p[:, dy:dy + 5, dx:dx + 6] for dy in range(size) for dx in range(size)],
                    -1)
    got = sampling.neighbourhood(jnp.asarray(x), size, mode=mode)
    assert got.shape == (2, 5, 6, 3, size * size)
    np.testing.assert_array_equal(got, want)
    if mode == "edge":  # the default
        np.testing.assert_array_equal(sampling.neighbourhood(jnp.asarray(x), size), want)


@pytest.mark.parametrize("mode", ["edge", "constant"])
def test_filter_neighbourhood_is_the_weighted_sum_of_the_neighbourhood(rng, mode, x64):
    """Per-pixel filtering equals the einsum of the stacked neighbourhood with the
    weights, in float64 to 1e-12 (a tap in the wrong place or order shows at O(1)), and
    in float32 to within rounding; so do its gradients in both arguments."""
    x = rng.normal(size=(2, 5, 6, 3))
    w = rng.normal(size=(2, 5, 6, 25))

    def want(x, w):
        return jnp.einsum("bhwcn,bhwn->bhwc", sampling.neighbourhood(x, 5, mode=mode), w)

    def got(x, w):
        return sampling.filter_neighbourhood(x, w, 5, mode=mode)

    np.testing.assert_allclose(got(jnp.asarray(x), jnp.asarray(w)),
                               want(jnp.asarray(x), jnp.asarray(w)), rtol=0, atol=1e-12)
    x32, w32 = jnp.asarray(x, jnp.float32), jnp.asarray(w, jnp.float32)
    np.testing.assert_allclose(got(x32, w32), want(x32, w32), rtol=0, atol=1e-5)
    g = jax.grad(lambda x, w: jnp.sum(jnp.sin(got(x, w))), (0, 1))(jnp.asarray(x), jnp.asarray(w))
    r = jax.grad(lambda x, w: jnp.sum(jnp.sin(want(x, w))), (0, 1))(jnp.asarray(x), jnp.asarray(w))
    for a, b in zip(g, r):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("factor", [2, 4])
def test_jitted_gradient_of_bilinear_upsampling_equals_torch(rng, factor):
    """The jitted input gradients of plain and jitter-aligned bilinear up-sampling (NSRR's
    U-Net, DLCTUS's JAU) against torch's autograd through ``F.interpolate`` and through
    the PyTorch KPN reference's ``grid_sample`` JAU, at a batch of 2 x 16 x 16 x 8.
    A one-sum form of the dense up-sampling compiled here (jaxlib 0.10.2, XLA:CPU's
    YNNPACK reduction fusion) to gradients off by 5-20 or not finite; float32 rounding
    is 1e-6."""
    import torch
    import torch.nn.functional as F

    from jtus.reference import torch_kpn

    x = rng.normal(size=(2, 16, 16, 8)).astype(np.float32)
    g = rng.normal(size=(2, 16 * factor, 16 * factor, 8)).astype(np.float32)
    jit = rng.uniform(size=(2, 2)).astype(np.float32)
    nchw = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))  # noqa: E731
    for name, fn, ref in (
            ("upsample", lambda v: sampling.upsample(v, factor),
             lambda t: F.interpolate(t, scale_factor=factor, mode="bilinear",
                                     align_corners=False)),
            ("jitter_aligned_upsample",
             lambda v: sampling.jitter_aligned_upsample(v, jnp.asarray(jit), factor),
             lambda t: torch_kpn.jau(t, torch.from_numpy(jit), factor))):
        grad = jax.jit(lambda x, g, fn=fn: jax.vjp(fn, x)[1](g)[0])
        got = np.asarray(grad(jnp.asarray(x), jnp.asarray(g)))
        t = nchw(x).requires_grad_()
        ref(t).backward(nchw(g))
        want = t.grad.numpy().transpose(0, 2, 3, 1)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5, err_msg=name)


def test_jitter_cell_clamps_into_the_lr_pixel():
    """floor(jitter * f), clamped to [0, f-1]: jitter 1.0 (the upper edge) is the last
    cell, a rounding below 0 the first; int32 cells."""
    jit = jnp.asarray([[-1e-7, 1.0], [0.0, 0.999], [0.26, 0.5], [0.74, 0.2499]], jnp.float32)
    cells = sampling.jitter_cell(jit, 4)
    assert cells.dtype == jnp.int32
    np.testing.assert_array_equal(cells, [[0, 3], [0, 3], [1, 2], [2, 0]])
    np.testing.assert_array_equal(sampling.jitter_cell(jit, 2), [[0, 1], [0, 1], [0, 1], [1, 0]])


def test_hr_to_lr_coords_are_hr_centres_in_lr_units():
    from jtus.sampling.upsample import hr_to_lr_coords
    xy = hr_to_lr_coords(2, 1, 2, 4, jnp.bfloat16)
    assert xy.shape == (2, 4, 8, 2) and xy.dtype == jnp.bfloat16
    np.testing.assert_array_equal(np.asarray(xy[1, 3, :, 0], np.float32),
                                  (np.arange(8) + 0.5) / 4)
    np.testing.assert_array_equal(np.asarray(xy[0, :, 5, 1], np.float32),
                                  (np.arange(4) + 0.5) / 4)


@pytest.mark.parametrize("factor", [3, 4])
def test_float32_upsampling_is_the_same_with_64_bit_types_on(rng, factor):
    """Up-sampling and JAU of float32 images (bilinear and bicubic) compute their
    positions and weights in float32 whether or not 64-bit types are on (the same bits,
    as training and the float64 references run side by side)."""
    x = jnp.asarray(rng.normal(size=(3, 4, 5, 2)), jnp.float32)
    jit = jnp.asarray(rng.uniform(0, 1, size=(3, 2)), jnp.float32)

    def both():  # bilinear (dense stencil) and bicubic (sampled) of each
        return (sampling.upsample(x, factor), sampling.jitter_aligned_upsample(x, jit, factor),
                sampling.upsample(x, factor, method="bicubic"),
                sampling.jitter_aligned_upsample(x, jit, factor, method="bicubic"))
    off = both()
    with jax.enable_x64(True):
        on = both()
    for a, b in zip(on, off):
        assert a.dtype == jnp.float32
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("factor", [2, 3])
def test_catmull_rom_upsampling_reproduces_quadratics(x64, factor):
    """Keys's cubic convolution with a=-0.5 reproduces every quadratic exactly (Keys
    1981, sec. III), a=-0.75 does not: up-sampling (plain and jitter-aligned) a quadratic
    ramp with ``method="bicubic", a=-0.5`` gives the quadratic at each HR position whose
    four taps per axis lie inside the image, and ``a`` is the one asked for."""
    b, h, w = 2, 8, 9
    q = lambda X, Y: 0.3 + 0.2 * X - 0.1 * Y + 0.05 * X * X - 0.03 * X * Y + 0.02 * Y * Y  # noqa: E731
    Yl, Xl = np.mgrid[0:h, 0:w] + 0.5                       # LR pixel centres
    x = jnp.asarray(np.broadcast_to(q(Xl, Yl)[None, :, :, None], (b, h, w, 1)))
    jit = jnp.asarray([[0.5, 0.5], [0.2, 0.7]])
    for name, j, up in (
            ("upsample", np.full((b, 2), 0.5),
             lambda a: sampling.upsample(x, factor, method="bicubic", a=a)),
            ("jau", jit, lambda a: sampling.jitter_aligned_upsample(x, jit, factor,
                                                                    method="bicubic", a=a))):
        pos = seqdata.jau_positions(j, h, w, factor)
        inner = np.all((pos >= 2) & (pos <= np.array([w, h]) - 2), -1)   # taps inside
        assert inner.sum() > 20
        for a, exact in ((-0.5, True), (-0.75, False)):
            err = np.abs(np.asarray(up(a))[..., 0] - q(pos[..., 0], pos[..., 1]))[inner]
            if exact:
                assert err.max() < 1.2e-14, (name, err.max())  # measured: up to 5.8e-15
            else:
                assert err.max() > 1e-2, (name, err.max())     # measured 0.040-0.048


def test_factor_one_upsampling_is_the_identity(rng):
    """Factor 1 (native resolution, as ``fsr2(1)`` serves): plain and jitter-aligned
    up-sampling at jitter 0.5 return the image."""
    x = jnp.asarray(rng.normal(size=(2, 4, 5, 3)), jnp.float32)
    for method in ("bilinear", "bicubic", "nearest"):
        np.testing.assert_allclose(sampling.upsample(x, 1, method=method), x, atol=1e-6)
        np.testing.assert_allclose(sampling.jitter_aligned_upsample(
            x, jnp.full((2, 2), 0.5), 1, method=method), x, atol=1e-6)


def test_zero_upsample_keeps_the_input_dtype():
    jit = jnp.asarray([[0.1, 0.9]])
    x = jnp.ones((1, 2, 2, 1))
    assert sampling.zero_upsample(x.astype(jnp.bfloat16), jit, 2).dtype == jnp.bfloat16
    with jax.enable_x64(True):
        assert sampling.zero_upsample(x, jit, 2).dtype == jnp.float32


def test_reproject_coords_are_hr_centres_plus_upsampled_motion(x64, rng):
    """HR pixel centres (X + 0.5, Y + 0.5) plus f times the LR motion up-sampled
    bilinearly (``F.interpolate``, align_corners False: ``seqdata.jau_reference`` at
    jitter 0.5); half-precision motion gives float32 positions."""
    f, h, w = 4, 3, 5
    mv = rng.uniform(-2, 2, size=(2, h, w, 2))
    got = np.asarray(sampling.reproject_coords(jnp.asarray(mv), f))
    up = seqdata.jau_reference(mv, np.full((2, 2), 0.5), f)
    Y, X = np.mgrid[0:h * f, 0:w * f] + 0.5
    want = np.stack([X, Y], -1)[None] + f * up
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert sampling.reproject_coords(jnp.asarray(mv, jnp.float16), f).dtype == jnp.float32


def test_upsample_bad_inputs():
    with pytest.raises(ValueError, match="factor"):
        sampling.pixel_unshuffle(jnp.zeros((1, 6, 6, 1)), 4)
    for hh, ww in ((4, 3), (3, 4)):  # either side not divisible
        with pytest.raises(ValueError, match=f"x: size {hh}x{ww} not divisible by factor 2"):
            sampling.pixel_unshuffle(jnp.zeros((1, hh, ww, 1)), 2)
    with pytest.raises(ValueError, match="x: channels 6 not divisible by factor\\^2=4"):
        sampling.pixel_shuffle(jnp.zeros((1, 2, 2, 6)), 2)
    for factor in (0, 2.0):
        with pytest.raises(ValueError, match=f"factor: expected a positive int, got {factor}"):
            sampling.pixel_shuffle(jnp.zeros((1, 2, 2, 4)), factor)
    with pytest.raises(ValueError, match=r"depth: expected \(1, 3, 3, 1\), got \(1, 3, 3, 2\)"):
        sampling.dilate_motion(jnp.zeros((1, 3, 3, 2)), jnp.zeros((1, 3, 3, 2)))
    with pytest.raises(ValueError, match=r"jitter: expected \[B,2\] with B=2, got \(1, 2\)"):
        sampling.zero_upsample(jnp.zeros((2, 3, 3, 1)), jnp.zeros((1, 2)), 2)
    with pytest.raises(ValueError, match="factor"):
        sampling.upsample(jnp.zeros((1, 3, 3, 1)), 2.5)


def test_van_der_corput_and_halton():
    assert [sampling.van_der_corput(i, 2) for i in range(1, 5)] == [0.5, 0.25, 0.75, 0.125]
    np.testing.assert_allclose([sampling.van_der_corput(i, 3) for i in range(1, 5)],
                               [1 / 3, 2 / 3, 1 / 9, 4 / 9])
    h = sampling.halton(8)
    np.testing.assert_allclose(h[0], [0.5, 1 / 3])
    assert np.all((h >= 0) & (h < 1))


def _neighbours(a, b):
    return max(abs(a[0] - b[0]), abs(a[1] - b[1])) <= 1


def test_thesis_4x4_pattern():
    seq = sampling.thesis_4x4()
    assert seq.shape == (16, 2)
    cells = seq * 4 - 0.5
    np.testing.assert_array_equal(cells, np.round(cells))  # at HR-pixel centres
    cells = [tuple(c) for c in cells.astype(int)]
    assert sorted(cells) == [(x, y) for x in range(4) for y in range(4)]
    for t in range(16):  # cyclically: the sequence repeats
        assert not _neighbours(cells[t], cells[(t + 1) % 16]), t


def test_thesis_2x2_pattern():
    seq = sampling.thesis_2x2()
    assert seq.shape == (16, 2)
    halton = sampling.halton(4, start=2)
    cells = [(0, 0), (1, 0), (0, 1), (1, 1)]
    for t in range(16):
        cell = np.floor(seq[t] * 2)
        assert tuple(cell.astype(int)) == cells[t % 4]  # hourglass order
        np.testing.assert_allclose(seq[t] * 2 - cell, halton[t // 4])
    assert len({tuple(p) for p in seq}) == 16


@pytest.mark.parametrize("factor,n", [(2, 32), (4, 128), (1.5, 18)])
def test_fsr2_length(factor, n):
    seq = sampling.fsr2(factor)
    assert seq.shape == (n, 2)
    np.testing.assert_allclose(seq, sampling.halton(n))
    assert len({tuple(p) for p in seq}) == n


def test_jitter_sequence_names():
    seq = sampling.jitter_sequence
    np.testing.assert_array_equal(seq("thesis", 4), sampling.thesis_4x4())
    np.testing.assert_array_equal(seq("thesis", 2), sampling.thesis_2x2())
    np.testing.assert_array_equal(seq("halton", 4, length=5), sampling.halton(5))
    np.testing.assert_array_equal(seq("halton", 2), sampling.halton(16))  # default length
    np.testing.assert_array_equal(seq("halton8", 2), sampling.halton(8))
    np.testing.assert_array_equal(seq("halton32", 4), sampling.halton(32))
    np.testing.assert_array_equal(seq("halton120", 4), sampling.halton(120))
    np.testing.assert_array_equal(seq("fsr2", 2), sampling.fsr2(2))
    np.testing.assert_array_equal(seq("fsr2", 1.5), sampling.fsr2(1.5))
    for name in jitter.VARIETY:  # what the randomized data draws from
        assert seq(name, 4).shape[1] == 2
    with pytest.raises(ValueError, match="factor: the thesis patterns exist for 2 and 4, got 3"):
        seq("thesis", 3)
    for bad in ("sobol", "Halton8", "haltonx", "fsr", "8halton"):
        with pytest.raises(ValueError, match=r"name: expected one of \('thesis', 'halton', "
                                             r"'fsr2'\) or halton<N>, got '" + bad):
            seq(bad, 2)


def test_jitter_generators_reject_bad_arguments_by_name():
    """Each bound is where the docstring puts it: the edge value is accepted."""
    assert sampling.van_der_corput(0, 2) == 0.0 and sampling.van_der_corput(1, 2) == 0.5
    # (0, 0) first: with the bound's `or` turned into `and` it returns 0.0 at once, where
    # (-1, 2) or (3, 1) would loop for ever (divmod keeps n) and the mutant time out
    for n, base in ((0, 0), (-1, 1), (-1, 2), (3, 1)):
        with pytest.raises(ValueError, match=rf"van_der_corput: need n >= 0 and base >= 2, "
                                             rf"got n={n}, base={base}"):
            sampling.van_der_corput(n, base)
    np.testing.assert_array_equal(sampling.halton(1), [[0.5, 1 / 3]])
    np.testing.assert_array_equal(sampling.halton(2, start=0), [[0, 0], [0.5, 1 / 3]])
    np.testing.assert_allclose(sampling.halton(2, start=3, bases=(5, 7)),
                               [[3 / 5, 3 / 7], [4 / 5, 4 / 7]], rtol=1e-15)
    for count in (0, -2):
        with pytest.raises(ValueError, match=rf"count: expected >= 1, got {count}"):
            sampling.halton(count)
    assert sampling.fsr2(1).shape == (8, 2)  # no up-sampling (native AA): 8 phases
    for factor in (0, -2):
        with pytest.raises(ValueError, match=rf"factor: expected > 0, got {factor}"):
            sampling.fsr2(factor)


@pytest.mark.parametrize("fwd,inv", [(sampling.rgb_to_ycocg, sampling.ycocg_to_rgb),
                                     (sampling.rgb_to_ycbcr, sampling.ycbcr_to_rgb)])
def test_colour_round_trip(x64, rng, fwd, inv):
    rgb = jnp.asarray(rng.uniform(size=(3, 5, 3)))
    np.testing.assert_allclose(inv(fwd(rgb)), rgb, atol=1e-14)


@pytest.mark.parametrize("fn", [sampling.rgb_to_ycocg, sampling.ycocg_to_rgb,
                                sampling.rgb_to_ycbcr, sampling.ycbcr_to_rgb])
def test_colour_transforms_keep_the_input_dtype(fn):
    """A half-precision or float32 image stays so (with 64-bit types on, a float64
    matrix would promote a float32 image)."""
    x = jnp.full((2, 3), 0.25)
    assert fn(x.astype(jnp.bfloat16)).dtype == jnp.bfloat16
    with jax.enable_x64(True):
        assert fn(x.astype(jnp.float32)).dtype == jnp.float32
        assert fn(x.astype(jnp.float64)).dtype == jnp.float64


def test_colour_known_values():
    white = jnp.ones((1, 3))
    np.testing.assert_allclose(sampling.rgb_to_ycocg(white), [[1, 0, 0]], atol=1e-7)
    np.testing.assert_allclose(sampling.rgb_to_ycbcr(white), [[1, 0.5, 0.5]], atol=1e-6)
    red = jnp.asarray([[1.0, 0, 0]])
    np.testing.assert_allclose(sampling.rgb_to_ycocg(red), [[0.25, 0.5, -0.25]], atol=1e-7)
