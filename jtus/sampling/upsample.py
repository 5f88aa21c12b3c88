"""Up-sampling, pixel shuffle and motion-vector dilation, NHWC.

``f`` is the integer up-sampling factor: a low-resolution (LR) image
``[B,h,w,C]`` maps to a high-resolution (HR) one ``[B,f*h,f*w,C]``, HR pixel
(Y, X) covering LR coordinates ``[X/f, (X+1)/f) x [Y/f, (Y+1)/f)``.
``jitter [B,2]`` is the sample's offset inside its LR pixel in [0,1)^2,
(x, y), as in ``docs/conventions.md``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jtus.sampling.warp import PYTORCH_A, WarpPlan, offset_plan, pixel_grid, sample


def _check_factor(factor):
    if not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor: expected a positive int, got {factor!r}")


def _check_jitter(x, jitter):
    if jitter.shape != (x.shape[0], 2):
        raise ValueError(f"jitter: expected [B,2] with B={x.shape[0]}, got {jitter.shape}")


def pixel_shuffle(x, factor):
    """``[B,h,w,C*f*f] -> [B,f*h,f*w,C]``, the channel order of ``torch.nn.PixelShuffle``
    (input channel ``c*f*f + dy*f + dx`` lands at sub-pixel (dy, dx) of channel c)."""
    _check_factor(factor)
    b, h, w, c = x.shape
    if c % (factor * factor):
        raise ValueError(f"x: channels {c} not divisible by factor^2={factor * factor}")
    co = c // (factor * factor)
    x = x.reshape(b, h, w, co, factor, factor)
    x = x.transpose(0, 1, 4, 2, 5, 3)  # b, h, dy, w, dx, c
    return x.reshape(b, h * factor, w * factor, co)


def pixel_unshuffle(x, factor):
    """Inverse of ``pixel_shuffle``: ``[B,f*h,f*w,C] -> [B,h,w,C*f*f]``."""
    _check_factor(factor)
    b, hh, ww, c = x.shape
    if hh % factor or ww % factor:
        raise ValueError(f"x: size {hh}x{ww} not divisible by factor {factor}")
    h, w = hh // factor, ww // factor
    x = x.reshape(b, h, factor, w, factor, c)
    x = x.transpose(0, 1, 3, 5, 2, 4)  # b, h, w, c, dy, dx
    return x.reshape(b, h, w, c * factor * factor)


def jitter_cell(jitter, factor):
    """Sub-pixel (x, y) of the HR pixel under the jittered sample, ints in [0,f)."""
    return jnp.clip(jnp.floor(jitter * factor).astype(jnp.int32), 0, factor - 1)


def zero_upsample(x, jitter, factor):
    """Place each LR sample at the HR pixel under its jittered position; zeros elsewhere.

    ``x [B,h,w,C]``, ``jitter [B,2]`` -> ``[B,f*h,f*w,C]``. Built as a product with
    a one-hot sub-pixel mask, so it is differentiable in ``x`` and jit-able with
    traced jitter.
    """
    _check_factor(factor)
    _check_jitter(x, jitter)
    cell = jitter_cell(jitter, factor)
    k = jnp.arange(factor)
    onehot_x = (k[None, :] == cell[:, 0:1]).astype(x.dtype)  # [B,f]
    onehot_y = (k[None, :] == cell[:, 1:2]).astype(x.dtype)
    mask = onehot_y[:, :, None] * onehot_x[:, None, :]  # [B,dy,dx]
    b, h, w, c = x.shape
    out = x[:, :, None, :, None, :] * mask[:, None, :, None, :, None]
    return out.reshape(b, h * factor, w * factor, c)


def hr_to_lr_coords(batch, height, width, factor, dtype=jnp.float32):
    """Centres of the HR pixels, ``[B,f*h,f*w,2]``, in LR pixel coordinates."""
    return pixel_grid(batch, height * factor, width * factor, dtype) / factor


def _phase_weights(d):
    """Bilinear weights of the taps at offsets -1, 0, 1 for fractional positions
    ``d`` in (-1, 1) (any shape): ``[..., 3]``. The tap at ``floor(d)`` gets ``1 - t``
    and the next one ``t``, ``t = d - floor(d)``; ``floor`` cuts no gradient, ``t``
    carries it."""
    fl = jnp.floor(d)
    t = d - fl
    lo = (fl < 0).astype(d.dtype)  # floor(d) = -1: taps -1, 0; else taps 0, 1
    return jnp.stack([(1 - t) * lo, (1 - t) * (1 - lo) + t * lo, t * (1 - lo)], -1)


def _one_sum(x, factor, wx, wy):
    """``_bilinear_phases``'s value: one fusion writing ``[B,h,f,w,f,C]`` (row-major, so
    the HR image is a reshape) in which every tap is a broadcast slice of the
    edge-padded LR image, x first and then y (the warp's order). Stacking per-phase
    results instead made XLA:CPU materialize them through slow concatenations."""
    b, h, w, c = x.shape
    p = pad_edge(x, 1)
    out = 0
    for ky in range(3):
        row = 0
        for kx in range(3):
            tap = p[:, ky:ky + h, None, kx:kx + w, None, :]  # [B,h,1,w,1,C]
            row = row + tap * wx[:, None, None, None, :, kx, None]
        out = out + row * wy[:, None, :, None, None, ky, None]
    return out.reshape(b, h * factor, w * factor, c)


def _two_passes(x, factor, wx, wy):
    """The same values as a pass along x (every x phase of the padded rows) and then one
    along y: the form ``_bilinear_phases`` differentiates. Each phase is its own slice
    product, stacked at the end, so that the transpose reads each phase as a slice of
    the output gradient: a tap broadcast across the phases instead transposes into a
    sum over a size-``factor`` axis, which XLA:CPU runs as slow YNNPACK reductions (NSRR's
    training step took 1.12-1.14x the time, docs/results/comparison-train-ab-slices/)."""
    b, h, w, c = x.shape
    p = pad_edge(x, 1)
    rows = []  # per x phase: [B,h+2,w,C]
    for px in range(factor):
        row = 0
        for kx in range(3):
            row = row + p[:, :, kx:kx + w, :] * wx[:, None, None, px, kx, None]
        rows.append(row)
    out = []  # per y phase: [B,h,w,f,C]
    for py in range(factor):
        cols = []
        for row in rows:
            col = 0
            for ky in range(3):
                col = col + row[:, ky:ky + h] * wy[:, None, None, py, ky, None]
            cols.append(col)
        out.append(jnp.stack(cols, 3))
    return jnp.stack(out, 2).reshape(b, h * factor, w * factor, c)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _phases(x, factor, wx, wy):
    return _one_sum(x, factor, wx, wy)


def _phases_fwd(x, factor, wx, wy):
    return _one_sum(x, factor, wx, wy), (x, wx, wy)


def _phases_bwd(factor, res, g):
    x, wx, wy = res
    return jax.vjp(lambda *a: _two_passes(a[0], factor, *a[1:]), x, wx, wy)[1](g)


_phases.defvjp(_phases_fwd, _phases_bwd)


def _bilinear_phases(x, factor, wx, wy):
    """Dense bilinear up-sampling by an integer factor when the sampling positions
    repeat with period ``factor``: HR pixel ``f*J + p`` reads LR index ``J + d_p``.

    ``wx``, ``wy`` ``[B,f,3]``: the weights of LR offsets -1, 0, 1 per phase (from
    ``_phase_weights``). Border taps replicate the edge, as the warp does, so this
    equals ``sample(..., "bilinear")`` at those positions, without gathers. Gradients
    are dense too (no scatter-add).

    The value is one sum of the nine taps (``_one_sum``); the gradients are those of
    the same values computed in two passes (``_two_passes``). XLA:CPU (jaxlib 0.10.2)
    compiles the one-sum form's jitted gradient into a YNNPACK reduction fusion that
    returns wrong values, uninitialized memory among them, for batches above one or more
    than a few channels (``tests/test_upsample_jitter.py::
    test_jitted_gradient_of_bilinear_upsampling_equals_torch``); the two-pass gradient is
    right and took a third of the time (``docs/performance.md``, "Training the comparison
    systems"). As a value the two-pass form measured slower in DLCTUS's inference frame,
    so the value is the one sum."""
    return _phases(x, factor, wx.astype(x.dtype), wy.astype(x.dtype))


def upsample(x, factor, method="bilinear", a=-0.75):
    """Plain up-sampling (no jitter): HR pixel centres sampled in the LR image.

    With ``bilinear`` this equals ``F.interpolate(mode='bilinear',
    align_corners=False)``; it is how motion vectors are brought to HR (values
    are not rescaled: multiply by ``f`` for HR-pixel units). Bilinear runs as a
    dense fixed-stencil filter (``_bilinear_phases``); the other methods sample.
    """
    _check_factor(factor)
    b, h, w, _ = x.shape
    if method == "bilinear":
        dt = jnp.promote_types(x.dtype, jnp.float32)
        d = (jnp.arange(factor, dtype=dt) + 0.5) / factor - 0.5  # in (-0.5, 0.5)
        wt = jnp.broadcast_to(_phase_weights(d), (b, factor, 3))
        return _bilinear_phases(x, factor, wt, wt)
    return sample(x, hr_to_lr_coords(b, h, w, factor, x.dtype), method=method, a=a)


def jitter_aligned_upsample(x, jitter, factor, method="bilinear", a=-0.75):
    """Jitter-aligned up-sampling (JAU, thesis sec. 4.1.1).

    LR sample (i, j) was rendered at LR position ``(j, i) + jitter``; sampling
    the LR image at ``p - jitter + 0.5`` for each HR centre ``p`` puts that
    sample exactly under its true position. Bilinear runs as a dense fixed-stencil
    filter with per-frame weights (jitter in [0, 1] keeps every position within one
    LR pixel of its own); the other methods sample.
    """
    _check_factor(factor)
    _check_jitter(x, jitter)
    b, h, w, _ = x.shape
    if method == "bilinear":
        dt = jnp.promote_types(x.dtype, jnp.float32)
        base = (jnp.arange(factor, dtype=dt) + 0.5) / factor      # [f]
        j = jitter.astype(dt)
        wx = _phase_weights(base[None, :] - j[:, 0:1])                      # [B,f,3]
        wy = _phase_weights(base[None, :] - j[:, 1:2])
        return _bilinear_phases(x, factor, wx, wy)
    return sample(x, jitter_aligned_coords(jitter, b, h, w, factor, x.dtype), method=method,
                  a=a)


def jitter_aligned_coords(jitter, batch, height, width, factor, dtype=jnp.float32):
    """Where each HR pixel of a ``height x width`` LR frame reads it, ``[B,f*H,f*W,2]``
    in LR pixels: the HR centre minus the frame's ``jitter [B,2]``, plus 0.5 (the
    position ``jitter_aligned_upsample`` samples, which puts each sample under its true
    position)."""
    xy = hr_to_lr_coords(batch, height, width, factor, dtype)
    return xy - jitter.astype(dtype)[:, None, None, :] + 0.5


def neighbourhood_box(color, xy, with_mean=False):
    """Per HR pixel, the min and max (and, with ``with_mean``, the mean) of the 3x3 LR
    samples of ``color [B,h,w,C]`` around the sample nearest ``xy`` (LR pixels, as
    ``jitter_aligned_coords``), each tap clamped to the image: ``[B,H,W,C]`` each. The
    box that temporal anti-aliasing clamps a history to.

    Taken once at LR and gathered once: the image is edge-padded by one pixel first,
    so that a nearest sample just outside the image (a jitter can put it there) keeps
    the statistics of its own clamped taps, which makes this equal, value for value,
    to gathering the 9 clamped nearest samples at HR (the test's reference)."""
    n = neighbourhood(pad_edge(color, 1), 3)  # [B,h+2,w+2,C,9]
    stats = [n.min(-1), n.max(-1)] + ([n.mean(-1)] if with_mean else [])
    c = color.shape[-1]
    got = sample(jnp.concatenate(stats, -1), xy + 1.0, "nearest")
    return [got[..., i * c:(i + 1) * c] for i in range(len(stats))]


def pad_edge(x, p):
    """Replicate the border of ``x [B,H,W,C]`` by ``p`` pixels on H and W.

    Equal to ``jnp.pad(x, ((0, 0), (p, p), (p, p), (0, 0)), mode="edge")``, written as
    one concatenation per spatial axis: ``jnp.pad`` also emits zero-width slices for the
    unpadded axes, which jax2onnx 0.17 lowers to Reshapes onnxruntime rejects."""
    if p == 0:
        return x
    x = jnp.concatenate([x[:, :1]] * p + [x] + [x[:, -1:]] * p, axis=1)
    return jnp.concatenate([x[:, :, :1]] * p + [x] + [x[:, :, -1:]] * p, axis=2)


def _padded_taps(x, size, mode):
    """The padded image and the ``size * size`` shifted views of it, raster order."""
    r = size // 2
    h, w = x.shape[1:3]
    if mode == "edge":
        p = pad_edge(x, r)
    else:
        p = jnp.pad(x, ((0, 0), (r, r), (r, r), (0, 0)), mode=mode)
    return [p[:, dy:dy + h, dx:dx + w] for dy in range(size) for dx in range(size)]


def neighbourhood(x, size, mode="edge"):
    """``[B,H,W,C] -> [B,H,W,C,size*size]``: each pixel's ``size`` x ``size``
    neighbourhood in raster order (row by row), padded with ``mode`` (``"edge"``
    replicates, ``"constant"`` pads zeros). Stacked on a new leading axis and then
    moved last: XLA:CPU writes a stack whose new axis is the fastest-varying one about
    half as fast (docs/performance.md)."""
    return jnp.moveaxis(jnp.stack(_padded_taps(x, size, mode), 0), 0, -1)


def _filter_einsum(x, weights, size, mode):
    return jnp.einsum("bhwcn,bhwn->bhwc", neighbourhood(x, size, mode), weights)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def filter_neighbourhood(x, weights, size, mode="edge"):
    """Per-pixel filtering, ``[B,H,W,C]`` with ``weights [B,H,W,size*size]`` (raster
    order): ``einsum("bhwcn,bhwn->bhwc", neighbourhood(x, size, mode), weights)``.

    The forward pass is a sum of the shifted views times their weights, which XLA fuses
    into one loop: the stacked neighbourhood, whose taps are its fastest-varying axis,
    is never built (XLA:CPU writes such a stack slowly; KPN's two 5x5 stacks were half
    of its frame, docs/performance.md). The backward pass is the einsum's, which
    builds the stack once: the forward sum's own autodiff backward (one slice or pad
    per tap for both arguments) measured slower in KPN's training step. The same
    values as the einsum up to float rounding, and its gradients."""
    return _filter_sum(x, weights, size, mode)


def _filter_sum(x, weights, size, mode):
    out = None
    taps = jnp.split(weights.astype(x.dtype), size * size, axis=-1)
    for view, w in zip(_padded_taps(x, size, mode), taps):
        out = view * w if out is None else out + view * w
    return out


def _filter_fwd(x, weights, size, mode):
    return _filter_sum(x, weights, size, mode), (x, weights)


def _filter_bwd(size, mode, res, g):
    return jax.vjp(lambda x, w: _filter_einsum(x, w, size, mode), *res)[1](g)


filter_neighbourhood.defvjp(_filter_fwd, _filter_bwd)


_CENTRE_FIRST = (4, 0, 1, 2, 3, 5, 6, 7, 8)  # 3x3 raster indices, the centre first


def dilate_motion(motion, depth):
    """3x3 motion-vector dilation: each pixel takes the vector of its nearest neighbour.

    ``motion [B,h,w,2]``, ``depth [B,h,w,1]`` (device depth, smaller is nearer).
    Borders replicate the edge; on ties the centre pixel wins, then raster order.
    """
    if depth.shape != motion.shape[:3] + (1,):
        raise ValueError(f"depth: expected {motion.shape[:3] + (1,)}, got {depth.shape}")
    order = jnp.asarray(_CENTRE_FIRST)
    mvs = neighbourhood(motion, 3)[..., order]   # [B,h,w,2,9]
    ds = neighbourhood(depth, 3)[..., order]     # [B,h,w,1,9]
    best = jnp.argmin(ds, axis=-1)               # the first minimum wins
    return jnp.take_along_axis(mvs, best[..., None], axis=-1)[..., 0]


def reproject_coords(motion, factor):
    """Where each HR pixel of the current frame was in the previous one: the HR pixel
    centres plus the LR backward ``motion [B,h,w,2]`` up-sampled (bilinear) and scaled
    to HR pixels, ``[B,f*h,f*w,2]`` for ``sample``. Every model's history read and
    the temporal losses use this one position."""
    b, h, w, _ = motion.shape
    dt = jnp.promote_types(motion.dtype, jnp.float32)
    return pixel_grid(b, h * factor, w * factor, dt) + factor * upsample(motion, factor)


def reproject_plan(motion, factor, method="bilinear", a=PYTORCH_A,
                   dtype=jnp.float32) -> WarpPlan:
    """``warp_plan(reproject_coords(motion, factor), f*h, f*w, method, a, dtype)`` with
    the position kept as the HR pixel and its displacement ``f * upsample(motion)``
    (``offset_plan``): the read a recurrent model's history takes, at the position
    ``reproject_coords`` names, without the float32 rounding of the pixel centre plus
    the displacement (1.2e-4 px at 1080p)."""
    b, h, w, _ = motion.shape
    dt = jnp.promote_types(motion.dtype, jnp.float32)
    hh, ww = h * factor, w * factor
    index = jnp.stack(jnp.meshgrid(jnp.arange(ww, dtype=jnp.int32),
                                   jnp.arange(hh, dtype=jnp.int32), indexing="xy"), -1)
    d = factor * upsample(motion.astype(dt), factor)
    return offset_plan(jnp.broadcast_to(index, (b, hh, ww, 2)), d, hh, ww, method, a, dtype)
