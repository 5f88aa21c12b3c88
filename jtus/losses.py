"""Training losses (thesis sec. 4.3.3).

Every loss has the signature the rollout helper calls,
``loss(out, target, prev_out, prev_target, has_prev, frame) -> scalar``, with images
``[B,H,W,3]``. Temporal terms compare the current error ``x = out - target`` with
the previous frame's error warped to the current frame,
``y = f_prev(prev_out) - f_prev(prev_target) = f_prev(prev_out - prev_target)``,
where ``f_prev`` reads the previous image at ``P + f * up(motion)(P)`` (the
reprojection of ``docs/conventions.md``). Where there is no previous frame (the
start of a video, ``has_prev`` False) or the reprojection leaves the image, ``y = 0``.

- ``l1``, ``mse``;
- ``salvi`` (eq. 43): ``mean(x^2) + w * mean((x - y)^2)``, ``w`` the temporal weight
  (1 in the thesis);
- ``log-mse``: the batch mean of ``log(mean(x^2) + 1e-7)`` per crop (minus its PSNR up
  to scale and offset); ``log-salvi``: the same of Salvi's loss per crop,
  ``log(mean(x^2) + w * mean((x - y)^2) + 1e-7)``, so a flicker on a still surface (its
  error changing from frame to frame) costs relative to the crop's own error;
  ``log-salvi-unsampled``: the same with the temporal term counted only at the HR pixels
  that received no sample this frame (``m`` = 1 there, 0 under each LR sample's jittered
  position), ``log(mean(x^2) + w * mean(m * (x - y)^2) + 1e-7)``: an output pixel that
  got no new information should not change, one that got a sample may correct itself;
- ``st`` with θ (eq. 51-52): ``mean(x^2 + y^2 - 2θxy)``;
- ``st-linear`` with θ (eq. 54-55): ``mean(|x| + |y| + θ(|x - y| - |x| - |y|))``:
  θ=0 is the L1 of the current and the previous error, θ=1 the temporal term
  ``|x - y|``;
- ``ssim``: ``1 - SSIM``; ``ssim-srgb``: ``1 - SSIM`` of the sRGB-coded images
  (``sampling.srgb_encode``). SSIM's constants (C1 = 0.01², C2 = 0.03²) assume
  display-coded values; on linear colour they swamp errors in dark regions (a dark game
  level's linear values are a few thousandths), which the sRGB coding lifts 12.92-fold
  near black;
- ``kpn``: Herveau et al.'s alias-masked reference, gradient and temporal loss for
  their kernel-prediction network (``kpn_loss``).

Any of them takes NSRR's VGG-16 perceptual term on top when a weights file is given
(``make(..., perceptual_weights=FILE)``, ``jtus.perceptual``); nothing is downloaded.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from jtus import metrics, perceptual, sampling

NAMES = ("l1", "mse", "log-mse", "log-salvi", "log-salvi-unsampled", "salvi", "st", "st-linear",
         "ssim", "ssim-srgb", "kpn")


def warp_previous(prev, motion, factor, method):
    """``prev [B,H,W,C]`` read at the current frame's reprojected positions, and the
    mask ``[B,H,W,1]`` of positions inside the previous frame. ``motion`` is the LR
    backward motion ``[B,h,w,2]``."""
    xy = sampling.reproject_coords(motion.astype(prev.dtype), factor)
    return sampling.sample(prev, xy, method, return_mask=True)


def errors(out, target, prev_out, prev_target, has_prev, frame, factor, method="bilinear"):
    """The current error ``x`` and the warped previous error ``y`` (0 where none)."""
    x = out - target
    y, inside = warp_previous(prev_out - prev_target, frame.motion, factor, method)
    return x, jnp.where(inside & has_prev, y, 0.0)


def unsampled_mask(frame, factor):
    """``[B,H,W,1]``: 1 at the HR pixels no LR sample of ``frame`` landed on, 0 at the one
    pixel per LR pixel under the jittered sample (``sampling.zero_upsample``'s)."""
    ones = jnp.ones(frame.color.shape[:-1] + (1,), frame.color.dtype)
    return 1.0 - sampling.zero_upsample(ones, frame.jitter, factor)


def st_linear_terms(x, y, theta):
    return jnp.abs(x) + jnp.abs(y) + theta * (jnp.abs(x - y) - jnp.abs(x) - jnp.abs(y))


def _l1(out, target, *_):
    return jnp.mean(jnp.abs(out - target))


def _mse(out, target, *_):
    return jnp.mean(jnp.square(out - target))


LOG_MSE_FLOOR = 1e-7  # added to each crop's MSE before the log: PSNR 70 dB


def _per_crop(values):
    return jnp.mean(values, axis=tuple(range(1, values.ndim)))


def _log_mse(out, target, *_):
    """The mean over the batch of ``log(MSE + LOG_MSE_FLOOR)`` per crop: minus its PSNR up
    to scale and offset, so each crop's error counts relative to itself, as in a mean
    of per-frame PSNRs, and a dark crop weighs as much as a bright one."""
    return jnp.mean(jnp.log(_per_crop(jnp.square(out - target)) + LOG_MSE_FLOOR))


def _ssim(out, target, *_):
    return 1.0 - jnp.mean(metrics.ssim(out, target))


def _ssim_srgb(out, target, *_):
    return _ssim(sampling.srgb_encode(out), sampling.srgb_encode(target))


def _temporal(kind, theta, weight, factor, method, out, target, prev_out, prev_target,
              has_prev, frame):
    x, y = errors(out, target, prev_out, prev_target, has_prev, frame, factor, method)
    if kind == "salvi":
        return jnp.mean(x * x) + weight * jnp.mean(jnp.square(x - y))
    if kind in ("log-salvi", "log-salvi-unsampled"):
        change = jnp.square(x - y)
        if kind == "log-salvi-unsampled":
            change = change * unsampled_mask(frame, factor)
        per_crop = _per_crop(x * x) + weight * _per_crop(change)
        return jnp.mean(jnp.log(per_crop + LOG_MSE_FLOOR))
    if kind == "st":
        return jnp.mean(x * x + y * y - 2 * theta * x * y)
    return jnp.mean(st_linear_terms(x, y, theta))


def with_perceptual(base, weights_path, weight=0.1):
    """``base + weight * perceptual`` (NSRR's eq. 1 with ``base`` = 1 - SSIM), the
    perceptual term of ``jtus.perceptual`` on the VGG-16 weights in ``weights_path``."""

    if not weight >= 0.0:
        raise ValueError(f"perceptual_weight: expected a value >= 0, got {weight}")
    vgg_params = perceptual.load_vgg16(weights_path)

    def loss(out, target, *rest):
        return base(out, target, *rest) + weight * perceptual.loss(vgg_params, out, target)

    return loss


# the losses ``temporal_weight`` applies to
WEIGHTED_TEMPORAL = ("salvi", "log-salvi", "log-salvi-unsampled")


def make(name, factor, theta=0.5, method="bilinear", perceptual_weights=None,
         perceptual_weight=0.1, temporal_weight=1.0):
    """The loss ``name`` (one of ``NAMES``) for up-sampling factor ``factor``; with
    ``perceptual_weights`` (an ``.npz`` of VGG-16, see ``jtus.perceptual``) the
    perceptual term is added with weight ``perceptual_weight``. ``temporal_weight``
    scales the temporal term of ``WEIGHTED_TEMPORAL`` (the other losses have none, and
    ignore it)."""
    if not 0.0 <= temporal_weight < float("inf"):
        raise ValueError(f"temporal_weight: expected a finite value >= 0, got "
                         f"{temporal_weight}")
    plain = {"l1": _l1, "mse": _mse, "log-mse": _log_mse, "ssim": _ssim, "ssim-srgb": _ssim_srgb}
    if name in plain:
        base = plain[name]
    elif name in WEIGHTED_TEMPORAL + ("st", "st-linear"):
        if name in ("st", "st-linear") and not 0.0 <= theta <= 1.0:
            raise ValueError(f"theta: expected a value in [0, 1], got {theta}")
        base = functools.partial(_temporal, name, theta, temporal_weight, factor, method)
    elif name == "kpn":
        base = kpn_loss(factor)
    else:
        raise ValueError(f"loss: expected one of {NAMES}, got {name!r}")
    if perceptual_weights:
        base = with_perceptual(base, perceptual_weights, perceptual_weight)
    return displayed(base)


def displayed(fn):
    """``fn(out, target, prev_out, prev_target, has_prev, frame)`` on what a viewer
    sees: HDR frames (with an exposure) compare ``sampling.display`` of each image,
    tone-mapped pre-exposed colour in [0, 1), so highlights do not dominate; LDR frames
    (no exposure) compare the images themselves. Every loss and metric goes through it."""
    def on_display(out, target, prev_out, prev_target, has_prev, frame):
        e = None if frame is None else frame.exposure  # spatial losses need no frame
        if e is None:
            return fn(out, target, prev_out, prev_target, has_prev, frame)
        d = lambda x: sampling.display(x, e)  # noqa: E731
        return fn(d(out), d(target), d(prev_out), d(prev_target), has_prev,
                  frame._replace(color=d(frame.color)))
    return on_display


def alias_mask(jau, target, sensitivity=4.0):
    """Herveau et al.'s per-pixel aliasing mask: the summed channel differences between
    the (jitter-aligned) input and the reference, scaled, clipped to [0, 1], 3x3-dilated."""
    m = jnp.clip(sensitivity * jnp.abs(jau - target).sum(-1, keepdims=True), 0.0, 1.0)
    return sampling.neighbourhood(m, 3).max(-1)


def kpn_loss(factor, weights=(1.0, 1.0, 4.0), alias_boost=1.5, sensitivity=4.0):
    """Herveau et al.'s training loss for their kernel-prediction network (sec. 5.3):
    reference (L1), gradient (L1 of x and y differences) and temporal (the current
    error against the warped previous error) terms, each weighted by the alias mask M
    as ``alias_boost * M + (1 - M)``.

    The weights follow the paper's rule, not its number: the temporal term is scaled up
    by how much smaller it is than the reference term ("roughly ten times" in their
    anti-aliasing setting), so that it weighs most, then the gradient term, then the
    reference term (their Figure 7). Up-sampling 4x on the ``diverse`` data the
    unweighted terms of an initialized KPN are about 3x, not 10x, apart
    (``experiments/kpn_loss_terms.py``): a temporal weight of 4 keeps their order, where
    10 lets the temporal term outweigh the other two together (docs/results/kpn-loss/)."""
    wr, wg, wt = weights

    def grad(x):
        return x[:, 1:, :-1] - x[:, :-1, :-1], x[:, :-1, 1:] - x[:, :-1, :-1]

    def loss(out, target, prev_out, prev_target, has_prev, frame):
        jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                               frame.jitter.astype(jnp.float32), factor)
        m = alias_mask(jau, target, sensitivity)
        wgt = alias_boost * m + (1 - m)
        ref = jnp.mean(wgt * jnp.abs(out - target))
        gy_o, gx_o = grad(out)
        gy_t, gx_t = grad(target)
        wc = wgt[:, :-1, :-1]
        g = jnp.mean(wc * (jnp.abs(gy_o - gy_t) + jnp.abs(gx_o - gx_t)))
        x, y = errors(out, target, prev_out, prev_target, has_prev, frame, factor)
        t = jnp.mean(wgt * jnp.abs(x - y))
        return wr * ref + wg * g + wt * t

    return loss
