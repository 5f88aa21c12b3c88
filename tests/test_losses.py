"""Losses of thesis sec. 4.3.3, on hand-made cases."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import losses
from jtus.frame import Frame
from tests import seqdata


def _case(rng, factor=2, h=4, w=5, motion=None):
    shape = (1, h * factor, w * factor, 3)
    out, target, prev_out, prev_target = (jnp.asarray(rng.uniform(size=shape), jnp.float32)
                                          for _ in range(4))
    mv = np.zeros((1, h, w, 2), np.float32) if motion is None else motion
    return out, target, prev_out, prev_target, seqdata.frame_with_motion(mv)


def test_st_linear_endpoints(rng):
    out, target, prev_out, prev_target, frame = _case(rng)
    args = (out, target, prev_out, prev_target, jnp.asarray(True), frame)
    x, y = out - target, prev_out - prev_target  # zero motion: f_prev is the identity
    l0 = losses.make("st-linear", 2, theta=0.0)(*args)
    np.testing.assert_allclose(l0, jnp.mean(jnp.abs(x)) + jnp.mean(jnp.abs(y)), rtol=1e-6)
    l1 = losses.make("st-linear", 2, theta=1.0)(*args)
    np.testing.assert_allclose(l1, jnp.mean(jnp.abs(x - y)), rtol=1e-6)


@pytest.mark.parametrize("xv,yv,theta,expect", [
    (0.3, 0.1, 0.5, 0.4 + 0.5 * (0.2 - 0.4)),  # same sign: the temporal term helps
    (0.3, -0.1, 0.5, 0.4),                      # opposite signs: |x-y| = |x|+|y|
    (0.3, 0.3, 0.9, 0.6 - 0.9 * 0.6),
    (-0.2, -0.5, 0.1, 0.7 + 0.1 * (0.3 - 0.7)),
])
def test_st_linear_hand_computed(xv, yv, theta, expect):
    shape = (1, 4, 4, 3)
    target = jnp.full(shape, 0.5)
    out = target + xv
    prev_target = jnp.full(shape, 0.25)
    prev_out = prev_target + yv
    still = seqdata.frame_with_motion(np.zeros((1, 2, 2, 2), np.float32))
    loss = losses.make("st-linear", 2, theta=theta)(out, target, prev_out, prev_target,
                                                     jnp.asarray(True), still)
    np.testing.assert_allclose(loss, expect, rtol=1e-5)


def test_quadratic_st_and_salvi(rng):
    out, target, prev_out, prev_target, frame = _case(rng)
    args = (out, target, prev_out, prev_target, jnp.asarray(True), frame)
    x, y = out - target, prev_out - prev_target
    np.testing.assert_allclose(losses.make("st", 2, theta=0.3)(*args),
                               jnp.mean(x * x + y * y - 0.6 * x * y), rtol=1e-5)
    np.testing.assert_allclose(losses.make("salvi", 2)(*args),
                               jnp.mean(x * x) + jnp.mean((x - y) ** 2), rtol=1e-5)
    np.testing.assert_allclose(losses.make("salvi", 2, temporal_weight=2.5)(*args),
                               jnp.mean(x * x) + 2.5 * jnp.mean((x - y) ** 2), rtol=1e-5)


def test_log_salvi_is_the_batch_mean_of_log_salvi_per_crop(rng):
    """``log-salvi``: the batch mean of log(mean(x^2) + w mean((x - y)^2) + 1e-7) per crop,
    against numpy in float64 (1e-5); an error that stays put on a still surface costs
    what ``log-mse`` costs, and one that flips sign costs log(1 + 4w) more (its change is
    twice the error); with no previous frame y = 0, so the temporal part equals the
    spatial; w = 0 is log-mse; a negative or non-finite w is refused."""
    shape = (2, 8, 10, 3)
    target, prev_target = (rng.uniform(size=shape) * np.array([1.0, 0.02])[:, None, None, None]
                           for _ in range(2))
    x, y = (rng.normal(size=shape) * 0.01 for _ in range(2))
    frame = seqdata.frame_with_motion(np.zeros((2, 4, 5, 2), np.float32))
    loss = losses.make("log-salvi", 2)
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)

    def call(err, prev_err, has_prev=True):
        return float(loss(f32(target + err), f32(target), f32(prev_target + prev_err),
                          f32(prev_target), jnp.asarray(has_prev), frame))

    per_crop = (x ** 2).mean(axis=(1, 2, 3)) + ((x - y) ** 2).mean(axis=(1, 2, 3))
    np.testing.assert_allclose(call(x, y), np.mean(np.log(per_crop + 1e-7)), rtol=1e-5)
    log_mse = float(losses.make("log-mse", 2)(f32(target + x), f32(target), None, None, None,
                                               None))
    np.testing.assert_allclose(call(x, x), log_mse, rtol=1e-5)
    mse = (x ** 2).mean(axis=(1, 2, 3))
    np.testing.assert_allclose(call(x, -x), np.mean(np.log(5 * mse + 1e-7)), rtol=1e-5)
    np.testing.assert_allclose(call(x, y, has_prev=False), np.mean(np.log(2 * mse + 1e-7)),
                               rtol=1e-5)
    loss = losses.make("log-salvi", 2, temporal_weight=4.0)  # w * mean((x - y)^2)
    per_crop = (x ** 2).mean(axis=(1, 2, 3)) + 4.0 * ((x - y) ** 2).mean(axis=(1, 2, 3))
    np.testing.assert_allclose(call(x, y), np.mean(np.log(per_crop + 1e-7)), rtol=1e-5)
    np.testing.assert_allclose(call(x, -x), np.mean(np.log(17 * mse + 1e-7)), rtol=1e-5)
    loss = losses.make("log-salvi", 2, temporal_weight=0.0)
    np.testing.assert_allclose(call(x, -x), log_mse, rtol=1e-5)
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="temporal_weight: expected a finite value >= 0"):
            losses.make("log-salvi", 2, temporal_weight=bad)


@pytest.mark.parametrize("factor", [2, 4])
def test_log_salvi_unsampled_counts_the_change_only_where_no_sample_landed(rng, factor):
    """``log-salvi-unsampled``: log(mean(x^2) + w mean(m (x - y)^2) + 1e-7) per crop, ``m``
    zero at the one HR pixel per LR pixel under the frame's jittered sample, against numpy
    in float64 (1e-5); a change only at the sampled pixels costs nothing beyond
    ``log-mse``, the same change at an unsampled pixel does."""
    b, h, w = 2, 3, 4
    shape = (b, h * factor, w * factor, 3)
    target, prev_target = (rng.uniform(size=shape) for _ in range(2))
    x, y = (rng.normal(size=shape) * 0.01 for _ in range(2))
    jitter = np.array([[0.7, 0.2], [0.1, 0.9]], np.float32)
    frame = seqdata.frame_with_motion(np.zeros((b, h, w, 2), np.float32))._replace(
        jitter=jnp.asarray(jitter))
    m = np.ones(shape[:3] + (1,))
    for i, (jx, jy) in enumerate(jitter):  # the sampled pixel of every LR pixel
        m[i, int(jy * factor)::factor, int(jx * factor)::factor] = 0.0
    loss = losses.make("log-salvi-unsampled", factor, temporal_weight=3.0)
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)

    def call(err, prev_err):
        return float(loss(f32(target + err), f32(target), f32(prev_target + prev_err),
                          f32(prev_target), jnp.asarray(True), frame))

    per_crop = (x ** 2).mean(axis=(1, 2, 3)) + 3.0 * (m * (x - y) ** 2).mean(axis=(1, 2, 3))
    np.testing.assert_allclose(call(x, y), np.mean(np.log(per_crop + 1e-7)), rtol=1e-5)
    log_mse = float(losses.make("log-mse", factor)(f32(target + x), f32(target), None, None,
                                                    None, None))
    np.testing.assert_allclose(call(x, x + (1 - m) * y), log_mse, rtol=1e-5)
    assert call(x, x + m * y) > log_mse + 0.01
    np.testing.assert_array_equal(losses.unsampled_mask(frame, factor), m)


def test_previous_error_is_warped_with_motion(rng):
    """With a uniform motion of one LR pixel to the left (surfaces come from x + 1),
    the previous error is read f HR pixels to the right; outside it is 0."""
    f = 2
    mv = np.zeros((1, 4, 5, 2), np.float32)
    mv[..., 0] = 1.0
    out, target, prev_out, prev_target, frame = _case(rng, factor=f, motion=mv)
    x, y = losses.errors(out, target, prev_out, prev_target, jnp.asarray(True), frame, f)
    prev_err = np.asarray(prev_out - prev_target)
    np.testing.assert_allclose(np.asarray(y)[:, :, :-f], prev_err[:, :, f:], atol=1e-6)
    # The last column reads at x = W - 0.5 + 2 > W: outside, no previous error.
    np.testing.assert_array_equal(np.asarray(y)[:, :, -1], 0.0)


def test_previous_error_positions_in_the_errors_precision(rng):
    """The positions are computed in the errors' dtype: float32 errors and motion read
    the same with 64-bit types enabled as without (positions from float64 arithmetic
    differ by ~1e-6 pixels, which shows in the read values)."""
    f, h, w = 4, 6, 12
    mv = rng.uniform(-3, 3, size=(1, h, w, 2)).astype(np.float32)
    prev = rng.uniform(size=(1, h * f, w * f, 3)).astype(np.float32)
    reads = []
    for wide in (False, True):
        with jax.enable_x64(wide):
            reads.append(losses.warp_previous(jnp.asarray(prev), jnp.asarray(mv), f,
                                              "bilinear"))
    assert reads[1][0].dtype == jnp.float32
    np.testing.assert_array_equal(reads[1][0], reads[0][0])
    np.testing.assert_array_equal(reads[1][1], reads[0][1])


def test_no_previous_frame_reduces_to_l1(rng):
    out, target, prev_out, prev_target, frame = _case(rng)
    loss = losses.make("st-linear", 2, theta=0.7)(out, target, prev_out, prev_target,
                                                   jnp.asarray(False), frame)
    np.testing.assert_allclose(loss, jnp.mean(jnp.abs(out - target)), rtol=1e-6)


def test_loss_names_and_theta_checked():
    with pytest.raises(ValueError, match="loss"):
        losses.make("huber", 2)
    with pytest.raises(ValueError, match="theta"):
        losses.make("st-linear", 2, theta=1.5)


def _kpn_loss_numpy(out, target, prev_out, prev_target, color, jitter, f, has_prev,
                    weights=(1.0, 1.0, 4.0), boost=1.5, sensitivity=4.0):
    """Herveau et al.'s loss (sec. 5.3) written out in numpy (float64), with zero
    motion (the previous error then needs no warp): the alias mask is the summed
    absolute channel difference between the jitter-aligned input and the reference,
    times the sensitivity 4, clipped to [0, 1] and dilated 3x3 (the maximum over the
    in-frame neighbours); every term is weighted per pixel by 1.5 M + (1 - M); the
    gradient term compares forward differences along y and x on the pixels that have
    both; the temporal term compares the current error with the previous one. Weights
    1, 1, 4 (losses.kpn_loss's docstring says why 4)."""
    from tests.seqdata import jau_reference

    jau = jau_reference(color, jitter, f)
    m = np.clip(sensitivity * np.abs(jau - target).sum(-1), 0.0, 1.0)
    H, W = m.shape[1:]
    pad = np.pad(m, ((0, 0), (1, 1), (1, 1)), mode="edge")
    m = np.max([pad[:, dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)], 0)
    wgt = (boost * m + (1 - m))[..., None]
    ref = np.mean(wgt * np.abs(out - target) * np.ones(3))
    d = out - target
    gy = d[:, 1:, :-1] - d[:, :-1, :-1]
    gx = d[:, :-1, 1:] - d[:, :-1, :-1]
    grad = np.mean(wgt[:, :-1, :-1] * (np.abs(gy) + np.abs(gx)))
    prev = (prev_out - prev_target) if has_prev else 0.0
    temporal = np.mean(wgt * np.abs(d - prev))
    return weights[0] * ref + weights[1] * grad + weights[2] * temporal


@pytest.mark.parametrize("has_prev", [True, False])
def test_kpn_loss_against_its_formula(rng, has_prev):
    """Catches: the mask not dilated or not clipped, the boost on the wrong side of M,
    the gradient term dropped or cropped differently,
    the temporal term without the previous error, a weight changed."""
    from tests.seqdata import jau_reference

    f, b, h, w = 2, 2, 5, 6
    shape = (b, h * f, w * f, 3)
    out, prev_out, prev_target = (rng.uniform(size=shape) for _ in range(3))
    color = rng.uniform(size=(b, h, w, 3))
    jitter = np.array([[0.25, 0.75], [0.6, 0.1]])
    # the reference differs from the jitter-aligned input by nothing in the left third,
    # a little in the middle (M strictly between 0 and 1) and much on the right (M = 1),
    # so that the mask's scale, clip, dilation and the boost's side all show
    scale = np.select([np.arange(w * f) < 4, np.arange(w * f) < 8], [0.0, 0.03], 0.5)
    target = jau_reference(color, jitter, f) + rng.uniform(-1, 1, shape) * scale[:, None]
    m = np.clip(4.0 * np.abs(target - jau_reference(color, jitter, f)).sum(-1), 0, 1)
    assert (m == 0).any() and ((m > 0.05) & (m < 0.95)).any() and (m == 1).any()
    frame = Frame(jnp.asarray(color, jnp.float32), jnp.zeros((b, h, w, 1)),
                  jnp.zeros((b, h, w, 2)), jnp.asarray(jitter, jnp.float32))
    got = losses.kpn_loss(f)(*(jnp.asarray(x, jnp.float32) for x in
                               (out, target, prev_out, prev_target)),
                             jnp.asarray(has_prev), frame)
    want = _kpn_loss_numpy(out, target, prev_out, prev_target, color, jitter, f, has_prev)
    np.testing.assert_allclose(float(got), want, rtol=2e-6)  # float32 means of O(1) terms
    # every setting reaches the loss (a mutant dropping the sensitivity passed on to
    # alias_mask survived the defaults, which equal alias_mask's own)
    kw = dict(weights=(0.5, 2.0, 3.0), boost=2.5, sensitivity=2.0)
    got = losses.kpn_loss(f, kw["weights"], kw["boost"], kw["sensitivity"])(
        *(jnp.asarray(x, jnp.float32) for x in (out, target, prev_out, prev_target)),
        jnp.asarray(has_prev), frame)
    want = _kpn_loss_numpy(out, target, prev_out, prev_target, color, jitter, f, has_prev, **kw)
    np.testing.assert_allclose(float(got), want, rtol=2e-6)


def test_mse_and_ssim_losses_against_numpy_and_skimage():
    """The plain losses: L1 and MSE against numpy, NSRR's 1 - SSIM against scikit-image's SSIM
    (Gaussian window, sigma 1.5, population covariance: the metric's settings), batch
    mean; 1e-6."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(3)
    out, tgt = rng.uniform(size=(2, 2, 20, 24, 3)).astype(np.float32)
    rest = (None, None, None, None)
    mse = float(losses.make("mse", 4)(jnp.asarray(out), jnp.asarray(tgt), *rest))
    np.testing.assert_allclose(mse, np.mean((out.astype(np.float64) - tgt) ** 2), rtol=1e-6)
    l1 = float(losses.make("l1", 4)(jnp.asarray(out), jnp.asarray(tgt), *rest))
    np.testing.assert_allclose(l1, np.mean(np.abs(out.astype(np.float64) - tgt)), rtol=1e-6)
    ref = np.mean([structural_similarity(o, t, gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=1,
                                         channel_axis=-1) for o, t in zip(out, tgt)])
    ssim = float(losses.make("ssim", 4)(jnp.asarray(out), jnp.asarray(tgt), *rest))
    np.testing.assert_allclose(ssim, 1.0 - ref, rtol=0, atol=1e-6)
    assert float(losses.make("ssim", 4)(jnp.asarray(out), jnp.asarray(out), *rest)) == \
        pytest.approx(0.0, abs=1e-6)


def test_log_mse_loss_is_the_mean_per_crop_psnr_up_to_scale():
    """``log-mse``: the batch mean of log(each crop's MSE + 1e-7), against numpy and
    scikit-image's PSNR (-10 log10 MSE at data range 1) in float64 (1e-5); scaling one
    crop's error by k moves the loss by log(k^2) / B whatever the crop's brightness, so a
    dark crop's error counts as much as a bright one's."""
    from skimage.metrics import peak_signal_noise_ratio

    rng = np.random.default_rng(4)
    tgt = rng.uniform(size=(3, 10, 12, 3)) * np.array([1.0, 0.01, 0.3])[:, None, None, None]
    err = rng.normal(size=tgt.shape) * 0.02
    loss = losses.make("log-mse", 4)
    rest = (None, None, None, None)
    got = float(loss(jnp.asarray(tgt + err, jnp.float32), jnp.asarray(tgt, jnp.float32), *rest))
    want = np.mean(np.log((err ** 2).mean(axis=(1, 2, 3)) + 1e-7))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    psnr = np.mean([peak_signal_noise_ratio(t, t + e, data_range=1) for t, e in zip(tgt, err)])
    big = np.mean(np.log((err ** 2).mean(axis=(1, 2, 3))))  # without the floor
    np.testing.assert_allclose(-10 / np.log(10) * big, psnr, rtol=1e-9)
    for b in range(3):  # the same relative change for the dark crop as the bright one
        scaled = err.copy()
        scaled[b] *= 10.0
        moved = float(loss(jnp.asarray(tgt + scaled, jnp.float32), jnp.asarray(tgt, jnp.float32),
                           *rest))
        ratio = ((err[b] * 10) ** 2).mean() + 1e-7, (err[b] ** 2).mean() + 1e-7
        np.testing.assert_allclose(moved - got, np.log(ratio[0] / ratio[1]) / 3, rtol=1e-4)
        np.testing.assert_allclose(moved - got, np.log(100.0) / 3, rtol=1e-3)


def test_ssim_srgb_loss_is_ssim_of_the_srgb_coded_images():
    """``ssim-srgb``: 1 - SSIM (scikit-image, the metric's settings) of the images
    through the sRGB transfer function, which matches the numpy encoder of the image
    writers on [0, 1] (1e-6); dark linear values (a dark game level) weigh as much as
    bright ones once coded, so the loss is far larger than plain SSIM's there."""
    from skimage.metrics import structural_similarity

    from jtus import sampling
    from jtus.data.exr import linear_to_srgb

    rng = np.random.default_rng(4)
    out, tgt = rng.uniform(0, 0.02, size=(2, 2, 20, 24, 3)).astype(np.float32)
    enc = lambda x: linear_to_srgb(x.astype(np.float64))  # noqa: E731
    np.testing.assert_allclose(sampling.srgb_encode(jnp.asarray(out)), enc(out), atol=1e-6)
    rest = (None, None, None, None)
    ref = np.mean([structural_similarity(enc(o), enc(t), gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=1,
                                         channel_axis=-1) for o, t in zip(out, tgt)])
    got = float(losses.make("ssim-srgb", 4)(jnp.asarray(out), jnp.asarray(tgt), *rest))
    np.testing.assert_allclose(got, 1.0 - ref, rtol=0, atol=1e-6)
    plain = float(losses.make("ssim", 4)(jnp.asarray(out), jnp.asarray(tgt), *rest))
    assert got > 5 * plain, (got, plain)


def test_srgb_encode_is_monotone_with_finite_gradients_past_the_range():
    """A network's output below 0 or above 1 gets a finite gradient (the linear segment
    continues below 0, the power curve above 1) and the encoding stays monotone."""
    from jtus import sampling

    x = jnp.linspace(-0.5, 2.0, 2001)
    y = sampling.srgb_encode(x)
    assert bool(jnp.all(jnp.diff(y) > 0))
    g = jax.vmap(jax.grad(sampling.srgb_encode))(x)
    assert bool(jnp.all(jnp.isfinite(g))) and float(g.min()) > 0
    np.testing.assert_allclose(g[x <= sampling.color.SRGB_KNEE], 12.92, rtol=1e-6)


def test_kpn_loss_reads_low_precision_frames_in_float32(rng):
    """A half-precision frame (``Frame`` allows any floating dtype) gives the loss of
    the same values in float32: the jitter-aligned input the alias mask compares with
    is formed in float32, not in the frame's dtype (the loss casts, and the bilinear
    JAU promotes to float32 by itself, so mutating either alone changes nothing:
    tools/mutation.py lists those mutants as equivalent)."""
    f, b, h, w = 2, 1, 4, 5
    shape = (b, h * f, w * f, 3)
    out, target, prev_out, prev_target = (jnp.asarray(rng.uniform(size=shape), jnp.float32)
                                          for _ in range(4))
    color = jnp.asarray(rng.uniform(size=(b, h, w, 3)), jnp.float16)
    jitter = jnp.asarray([[0.3, 0.7]], jnp.float16)
    zeros = (jnp.zeros((b, h, w, 1)), jnp.zeros((b, h, w, 2)))
    half = Frame(color, *zeros, jitter)
    full = Frame(color.astype(jnp.float32), *zeros, jitter.astype(jnp.float32))
    loss = losses.kpn_loss(f)
    target = target.at[:, :, :4].set(0.0)  # a partial alias mask somewhere
    assert float(loss(out, target, prev_out, prev_target, jnp.asarray(True), half)) == \
        float(loss(out, target, prev_out, prev_target, jnp.asarray(True), full))


@pytest.mark.parametrize("method", ["bilinear", "catmull_rom"])
def test_temporal_loss_warps_with_the_method_it_is_given(rng, method):
    """``make(..., method=M)`` reads the previous error with warp M: the loss equals
    L_st-linear (eq. 55) on the previous error read by ``sampling.sample(..., M)`` at
    the reprojected positions (motion of a fraction of a pixel, so the warps differ),
    and the two methods give different losses."""
    from jtus import sampling

    f, h, w = 2, 6, 7
    mv = rng.uniform(-0.7, 0.7, size=(1, h, w, 2)).astype(np.float32)
    out, target, prev_out, prev_target, frame = _case(rng, factor=f, h=h, w=w, motion=mv)
    args = (out, target, prev_out, prev_target, jnp.asarray(True), frame)
    xy = sampling.reproject_coords(jnp.asarray(mv), f)
    y, inside = sampling.sample(prev_out - prev_target, xy, method, return_mask=True)
    x, y = np.asarray(out - target), np.where(np.asarray(inside), np.asarray(y), 0.0)
    theta = 0.4
    want = np.mean((1 - theta) * (np.abs(x) + np.abs(y)) + theta * np.abs(x - y))
    got = float(losses.make("st-linear", f, theta=theta, method=method)(*args))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    other = "catmull_rom" if method == "bilinear" else "bilinear"
    assert abs(got - float(losses.make("st-linear", f, theta=theta, method=other)(*args))) > 1e-4


def _shifted_previous_errors(f=4, shift=1, seed=5):
    """Current and previous outputs/targets and a frame whose LR motion is ``shift``
    LR pixels to the right everywhere: the previous value under HR pixel (y, x) is at
    (y, x + f*shift), inside the image only for x + f*shift < W (docs/conventions.md)."""
    from jtus.frame import Frame

    rng = np.random.default_rng(seed)
    B, H, W = 2, 16, 20
    out, target, prev_out, prev_target = (rng.uniform(size=(B, H, W, 3)) for _ in range(4))
    h, w = H // f, W // f
    motion = np.zeros((B, h, w, 2))
    motion[..., 0] = shift
    frame = Frame(jnp.zeros((B, h, w, 3)), jnp.full((B, h, w, 1), 0.5), jnp.asarray(motion),
                  jnp.full((B, 2), 0.5), None)
    x = out - target
    y = np.zeros_like(x)
    s = f * shift
    y[:, :, :W - s] = (prev_out - prev_target)[:, :, s:]  # f_prev, eq. 48
    args = tuple(jnp.asarray(a) for a in (out, target, prev_out, prev_target))
    return args, frame, x, y


def test_st_and_st_linear_follow_thesis_eq_48_to_55(x64):
    """L_st (eq. 51-52, and equal to eq. 48-49 divided by 1 + θ̂ with θ = θ̂/(1+θ̂))
    and L_st-linear (eq. 54-55), each the mean over pixels and channels of its
    per-element form, written here from the thesis, not from losses.py. Catches: a
    sign or factor of θ, the temporal term read at the wrong pixel or without the
    out-of-image mask, y not zeroed without a previous frame."""
    args, frame, x, y = _shifted_previous_errors()
    for theta in (0.0, 0.3, 0.5, 0.9):
        st = np.mean(x * x + y * y - 2 * theta * x * y)  # eq. 52
        th_hat = theta / (1 - theta)  # eq. 50's substitution, inverted
        st_hat = np.mean(x * x + y * y + th_hat * (x - y) ** 2)  # eq. 49
        np.testing.assert_allclose(st, st_hat / (1 + th_hat), rtol=1e-12)
        lin = np.mean(np.abs(x) + np.abs(y) + theta * (np.abs(x - y) - np.abs(x) - np.abs(y)))
        got_st = float(losses.make("st", 4, theta=theta)(*args, jnp.asarray(True), frame))
        got_lin = float(losses.make("st-linear", 4, theta=theta)(*args, jnp.asarray(True), frame))
        np.testing.assert_allclose(got_st, st, rtol=1e-12)
        np.testing.assert_allclose(got_lin, lin, rtol=1e-12)
    # no previous frame: y = 0, both reduce to the current error alone
    got = float(losses.make("st-linear", 4, theta=0.5)(*args, jnp.asarray(False), frame))
    np.testing.assert_allclose(got, np.mean(np.abs(x)), rtol=1e-12)
    got = float(losses.make("st", 4, theta=0.5)(*args, jnp.asarray(False), frame))
    np.testing.assert_allclose(got, np.mean(x * x), rtol=1e-12)
