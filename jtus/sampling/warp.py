"""Hand-written image warps: sample an image at continuous pixel coordinates.

Coordinates (see ``docs/conventions.md``): ``xy[..., 0]`` is x (to the right,
along the width), ``xy[..., 1]`` is y (down, along the height), in pixels of
the image being sampled, with the centre of pixel (row i, col j) at
``(j + 0.5, i + 0.5)``. The image covers ``[0, W] x [0, H]``.

Borders: every tap index is clamped into the image separately (replicate
padding). For bilinear that equals clamping the coordinate; for the cubic
kernels it does not, and it is what ``torch.nn.functional.grid_sample(...,
padding_mode='border')`` does. ``inside_mask`` tells which coordinates fall
outside the image, for callers (DLCTUS) that pad with something else.

All functions are pure JAX, jit-able and differentiable with respect to the
image and the coordinates (``floor`` cuts no gradient: the fractional part
carries it, so gradients are non-zero at pixel centres).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

METHODS = ("nearest", "bilinear", "bicubic", "catmull_rom", "bicubic9", "bicubic5")
# taps each method reads per output pixel and channel (for cost models, ``jtus.cost``)
TAPS = {"nearest": 1, "bilinear": 4, "bicubic": 16, "catmull_rom": 16, "bicubic9": 36,
        "bicubic5": 20}
CATMULL_ROM_A = -0.5
PYTORCH_A = -0.75


_FAR = float(2 ** 24)  # beyond this every tap is clamped to the edge pixel


def _check(image, xy):
    if image.ndim != 4:
        raise ValueError(f"image: expected [B,H,W,C], got shape {image.shape}")
    if xy.ndim != 4 or xy.shape[-1] != 2 or xy.shape[0] != image.shape[0]:
        raise ValueError(
            f"xy: expected [B,Ho,Wo,2] with B={image.shape[0]}, got shape {xy.shape}")


def _gather(image, iy, ix):
    """image [B,H,W,C]; integer iy, ix [B,...] (already clamped) -> [B,...,C].

    Read through one scalar index into the flattened image: the batched form
    (``vmap`` of ``image[y, x]``) builds a (batch, y, x) index vector per element,
    which XLA:CPU materializes through slow concatenations wherever the indices are
    shared between reads (TUS's step was several times slower for it)."""
    b, h, w, c = image.shape
    return image.reshape(b * h * w, c)[_flat_index(image.shape, iy, ix)]


def _flat_index(shape, iy, ix):
    """Index into ``image.reshape(B*H*W, C)`` of pixel ``(iy, ix)`` of each batch
    element; ``iy``, ``ix`` are ``[B,...]`` (broadcasting against each other)."""
    b, h, w, _ = shape
    batch = jnp.arange(b).reshape((b,) + (1,) * (max(iy.ndim, ix.ndim) - 1))
    return (batch * h + iy) * w + ix


def _taps(i0, n, size):
    """The ``n`` tap indices ``i0, i0 + 1, ...``, each clamped into ``[0, size)``."""
    return [jnp.clip(i0 + k, 0, size - 1) for k in range(n)]


def _rows(image, iy0, ix0, wy, wx):
    """``sum_j wy[..., j] * sum_i wx[..., i] * image[iy0 + j, ix0 + i]`` (each index
    clamped into the image), tap by tap, x first then y (PyTorch's order)."""
    h, w = image.shape[1:3]
    xs = _taps(ix0, wx.shape[-1], w)
    out = 0
    for j, yj in enumerate(_taps(iy0, wy.shape[-1], h)):
        row = 0
        for i, xi in enumerate(xs):
            row = row + _gather(image, yj, xi) * wx[..., i:i + 1]
        out = out + row * wy[..., j:j + 1]
    return out


@jax.checkpoint
def _all_taps(image, iy0, ix0, wy, wx):
    """``_rows`` as one gather of all taps on the flattened image. Checkpointed, so
    that a backward pass keeps only the per-axis ``iy0, ix0, wy, wx`` and rebuilds the
    ``ny * nx`` flat indices and weights itself (saving those per frame in a scan
    cost more than rebuilding them)."""
    b, h, w, c = image.shape
    iy = jnp.clip(iy0[..., None] + jnp.arange(wy.shape[-1]), 0, h - 1)  # [B,...,ny]
    ix = jnp.clip(ix0[..., None] + jnp.arange(wx.shape[-1]), 0, w - 1)
    idx = _flat_index(image.shape, iy[..., :, None], ix[..., None, :])  # [B,...,ny,nx]
    weights = (wy[..., :, None] * wx[..., None, :])[..., None]
    return (image.reshape(b * h * w, c)[idx] * weights).sum((-3, -2))


@jax.custom_jvp
def _separable(image, iy0, ix0, wy, wx):
    """A separable filter read: ``wy [B,...,ny]`` weighs rows ``iy0 [B,...] + j`` and
    ``wx [B,...,nx]`` columns ``ix0 + i`` (integer first taps; every tap index is
    clamped into the image separately, as ``grid_sample``'s border mode does);
    returns ``[B,...,C]``.

    The value is ``_rows``: one gather per tap, its index computed inside the
    gather's fusion. The tangent in the image is one gather of all ``ny * nx`` taps
    on the flattened image, so its transpose, the image gradient, is a single
    scatter-add: sixteen separate scatters (one per bicubic tap, each into its own
    zeroed buffer, then summed) cost about a fifth of a DLCTUS training step on
    XLA:CPU (docs/performance.md). Values and derivatives are the same function's;
    only the way XLA is asked to compute them differs.
    """
    return _rows(image, iy0, ix0, wy, wx)


def _separable_jvp(primals, tangents):
    image, iy0, ix0, wy, wx = primals
    t_image, _, _, t_wy, t_wx = tangents
    out = _rows(image, iy0, ix0, wy, wx)
    zero = jax.custom_derivatives.SymbolicZero
    t_out = jnp.zeros_like(out)
    if not isinstance(t_image, zero):
        t_out = _all_taps(t_image, iy0, ix0, wy, wx)
    if not isinstance(t_wy, zero):
        t_out = t_out + _rows(image, iy0, ix0, t_wy, wx)
    if not isinstance(t_wx, zero):
        t_out = t_out + _rows(image, iy0, ix0, wy, t_wx)
    return out, t_out


_separable.defjvp(_separable_jvp, symbolic_zeros=True)


def keys_weights(t, a):
    """Keys cubic-convolution weights of the taps at offsets -1, 0, 1, 2.

    ``t`` in [0, 1) is the distance from tap 0. ``a = -0.5`` is Catmull-Rom,
    ``a = -0.75`` PyTorch's bicubic. Returns a tuple of four arrays like ``t``.
    """
    def near(d):  # |d| <= 1
        return ((a + 2) * d - (a + 3)) * d * d + 1

    def far(d):  # 1 < |d| < 2
        return ((a * d - 5 * a) * d + 8 * a) * d - 4 * a

    return far(t + 1), near(t), near(1 - t), far(2 - t)


def _linear_weights(t):
    """``t [...,1]`` (the fractional part) -> ``[...,2]``: ``1 - t, t``, by a
    broadcast select rather than a concatenation, which XLA:CPU fuses badly."""
    return jnp.where(jnp.arange(2) == 0, 1 - t, t)


def _split(xy):
    """Pixel coordinates -> (integer tap-0 index, fractional part) per axis."""
    u = xy - 0.5  # index space: pixel centres at integers
    i0 = jnp.floor(u)
    return i0.astype(jnp.int32), (u - i0).astype(xy.dtype)


class WarpPlan(NamedTuple):
    """Where and how a warp reads, before the image is known: the part of ``sample``
    that depends on the coordinates only. A recurrent model computes it outside its
    ``lax.scan`` (for every frame at once) and reads the carried history through it
    inside (``warp_read``); ``sample`` is ``warp_read(image, warp_plan(...))``. The
    separable methods keep per-axis first taps and weights; ``bicubic9`` and
    ``bicubic5``, built from bilinear fetches, keep the coordinates."""
    iy0: Optional[jax.Array]  # [B,...] int32 first row tap (separable methods)
    ix0: Optional[jax.Array]  # [B,...] int32 first column tap
    wy: Optional[jax.Array]   # [B,...,ny] row weights
    wx: Optional[jax.Array]   # [B,...,nx] column weights
    xy: Optional[jax.Array]   # [B,...,2] the coordinates (bicubic9, bicubic5)
    inside: jax.Array         # [B,...,1] bool: ``inside_mask``


def warp_plan(xy, height, width, method="bilinear", a=PYTORCH_A,
              dtype=jnp.float32) -> WarpPlan:
    """The ``WarpPlan`` of reading a ``height x width`` image of ``dtype`` at ``xy
    [B,Ho,Wo,2]`` with ``method`` (``sample``'s arguments otherwise)."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if not jnp.issubdtype(xy.dtype, jnp.floating):
        xy = xy.astype(dtype if dtype == jnp.float64 else jnp.float32)
    xy = jnp.clip(xy, -_FAR, _FAR)
    inside = inside_mask(xy, height, width)
    if method in ("bicubic9", "bicubic5"):
        return WarpPlan(None, None, None, None, xy, inside)
    if method == "nearest":
        i0 = jnp.floor(xy).astype(jnp.int32)
        # one tap of weight 1; NaN coordinates give NaN through the weight
        one = jnp.where(jnp.isnan(xy).any(-1, keepdims=True), jnp.nan, 1).astype(dtype)
        return WarpPlan(i0[..., 1], i0[..., 0], one, one, None, inside)
    i0, t = _split(xy)
    return _separable_plan(i0, t, inside, method, a, dtype)


def _separable_plan(i0, t, inside, method, a, dtype):
    """The plan of a separable method from the index of the pixel centre at or left of
    (above) the position, ``i0 [B,...,2]`` int32, and the fractional part ``t``."""
    if method == "bilinear":
        wx, wy = (_linear_weights(t[..., k:k + 1].astype(dtype)) for k in (0, 1))
        return WarpPlan(i0[..., 1], i0[..., 0], wy, wx, None, inside)
    # 16 taps, Keys parameter a. Concatenated Keys weights: a broadcast form (as
    # ``_linear_weights``) was measured slower in DLCTUS's step at 1080p (XLA:CPU
    # split the read across two fusions).
    a = CATMULL_ROM_A if method == "catmull_rom" else a
    wx, wy = (jnp.concatenate(keys_weights(t[..., k:k + 1].astype(dtype), a), -1)
              for k in (0, 1))
    return WarpPlan(i0[..., 1] - 1, i0[..., 0] - 1, wy, wx, None, inside)


def offset_plan(index, d, height, width, method="bilinear", a=PYTORCH_A,
                dtype=jnp.float32) -> WarpPlan:
    """``warp_plan(index + 0.5 + d, ...)`` for a read displaced by ``d [B,Ho,Wo,2]``
    pixels (floating) from the centre of pixel ``index [B,Ho,Wo,2]`` (int32, x then y),
    without rounding that sum: the tap index is ``index + floor(d)`` and the fractional
    part ``d - floor(d)``, both exact, and ``inside`` compares ``d`` with the exact
    distances to the borders. In float32 the sum itself is rounded to the spacing of
    its magnitude (1.2e-4 px at x ~ 1900), which moves a 1080p read by up to 6e-5 px.
    The non-separable methods (``nearest``, ``bicubic9``, ``bicubic5``) read at the
    summed coordinates."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if index.shape != d.shape or d.shape[-1] != 2:
        raise ValueError(f"index, d: expected equal shapes [B,Ho,Wo,2], got {index.shape} "
                         f"and {d.shape}")
    if not jnp.issubdtype(d.dtype, jnp.floating):
        d = d.astype(jnp.float32)
    centre = index.astype(d.dtype) + 0.5
    if method in ("nearest", "bicubic9", "bicubic5"):
        return warp_plan(centre + d, height, width, method, a, dtype)
    d = jnp.clip(d, -_FAR, _FAR)
    whole = jnp.floor(d)
    i0 = index + whole.astype(jnp.int32)
    size = jnp.asarray([width, height], d.dtype)
    inside = ((d >= -centre) & (d <= size - centre)).all(-1, keepdims=True)
    return _separable_plan(i0, d - whole, inside, method, a, dtype)


def warp_read(image, p: WarpPlan, method="bilinear", a=PYTORCH_A):
    """Read ``image [B,H,W,C]`` through ``p`` (made by ``warp_plan`` for this image's size
    and dtype, with the same ``method`` and ``a``) -> ``[B,Ho,Wo,C]``."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if (p.xy is None) != (method not in ("bicubic9", "bicubic5")):
        raise ValueError(f"p: a WarpPlan made for another method than {method!r} (made with "
                         f"{'bicubic9 or bicubic5' if p.xy is not None else 'a separable one'})")
    if method == "bicubic9":
        return _bicubic9(image, p.xy, a)
    if method == "bicubic5":
        return _bicubic5(image, p.xy, a)
    return _separable(image, p.iy0, p.ix0, p.wy, p.wx)


def _bilinear_at(image, x, y):
    """Bilinear read at pixel coordinates ``x, y [...,1]``."""
    ix, tx = _split(x)
    iy, ty = _split(y)
    return _separable(image, iy[..., 0], ix[..., 0], _linear_weights(ty.astype(image.dtype)),
                      _linear_weights(tx.astype(image.dtype)))


def _three_fetches(i0, t, a, dtype):
    """Per axis: the 4 Keys taps as 3 linear fetches (positions, weights).

    The two inner taps have weights of one sign summing to w1 + w2 > 0, so one
    linear fetch between them at offset w2 / (w1 + w2) reproduces both; the
    outer taps are fetched at their pixel centres.
    """
    w0, w1, w2, w3 = keys_weights(t.astype(dtype), a)
    w12 = w1 + w2
    base = i0.astype(dtype) + 0.5  # centre of tap 0, in pixel coordinates
    pos = (base - 1, base + w2 / w12, base + 2)
    return pos, (w0, w12, w3)


def _bicubic9(image, xy, a):
    i0, t = _split(xy)
    px, wx = _three_fetches(i0[..., 0], t[..., 0], a, image.dtype)
    py, wy = _three_fetches(i0[..., 1], t[..., 1], a, image.dtype)
    out = 0
    for y, wyk in zip(py, wy):
        for x, wxk in zip(px, wx):
            out = out + _bilinear_at(image, x[..., None], y[..., None]) * (wxk * wyk)[..., None]
    return out


def _bicubic5(image, xy, a):
    """Unreal Engine 4's 5-fetch approximation: the 9-fetch kernel without its
    four corner fetches, renormalized so that the weights sum to one."""
    i0, t = _split(xy)
    px, wx = _three_fetches(i0[..., 0], t[..., 0], a, image.dtype)
    py, wy = _three_fetches(i0[..., 1], t[..., 1], a, image.dtype)
    taps = ((1, 0), (0, 1), (1, 1), (2, 1), (1, 2))  # (x fetch, y fetch)
    out, total = 0, 0
    for jx, jy in taps:
        wk = wx[jx] * wy[jy]
        out = out + _bilinear_at(image, px[jx][..., None], py[jy][..., None]) * wk[..., None]
        total = total + wk
    return out / total[..., None]


def sample(image, xy, method="bilinear", a=PYTORCH_A, return_mask=False):
    """Sample ``image [B,H,W,C]`` at pixel coordinates ``xy [B,Ho,Wo,2]``.

    ``method``: ``nearest`` (the pixel containing the point), ``bilinear``,
    ``bicubic`` (16 taps, Keys parameter ``a``), ``catmull_rom`` (bicubic with
    a=-0.5), ``bicubic9`` (the same 16-tap kernel from 9 bilinear fetches),
    ``bicubic5`` (5 bilinear fetches, corner taps dropped). ``a`` is used by
    the three cubic methods other than ``catmull_rom``.

    Returns ``[B,Ho,Wo,C]`` in the image's dtype, and with ``return_mask`` also
    ``inside_mask(xy, H, W)``. ``warp_read(image, warp_plan(xy, H, W, ...))``.
    NaN coordinates give NaN with every method. Integer images and coordinates are
    cast to floating point first (an integer coordinate 2 is the corner between
    pixels 1 and 2, as 2.0 is). Coordinates beyond ``±2**24`` pixels are clamped there:
    every tap is then the edge pixel whatever the fraction, so values and gradients
    are unchanged, and the integer tap indices cannot overflow.
    """
    _check(image, xy)
    if not jnp.issubdtype(image.dtype, jnp.floating):
        image = image.astype(jnp.float32)
    p = warp_plan(xy, *image.shape[1:3], method=method, a=a, dtype=image.dtype)
    out = warp_read(image, p, method, a)
    return (out, p.inside) if return_mask else out


def inside_mask(xy, height, width):
    """``[B,Ho,Wo,1]`` bool: True where ``xy`` lies in the image ``[0,W]x[0,H]``."""
    x, y = xy[..., 0:1], xy[..., 1:2]
    return (x >= 0) & (x <= width) & (y >= 0) & (y <= height)


def pixel_grid(batch, height, width, dtype=jnp.float32):
    """Centres of the pixels of a ``height x width`` image, ``[B,H,W,2]`` (x, y)."""
    x = jnp.arange(width, dtype=dtype) + 0.5
    y = jnp.arange(height, dtype=dtype) + 0.5
    g = jnp.stack(jnp.meshgrid(x, y, indexing="xy"), -1)
    return jnp.broadcast_to(g, (batch, height, width, 2))


def grid_sample(image, grid, method="bilinear", a=PYTORCH_A, align_corners=False):
    """``sample`` on PyTorch-style normalized grids ``[B,Ho,Wo,2]`` in [-1, 1].

    ``grid[..., 0]`` is x and ``grid[..., 1]`` is y as in
    ``torch.nn.functional.grid_sample``; borders behave like its
    ``padding_mode='border'`` (NHWC here, NCHW there).
    """
    _check(image, grid)
    h, w = image.shape[1:3]
    size = jnp.asarray([w, h], dtype=grid.dtype)
    if align_corners:
        xy = (grid + 1) / 2 * (size - 1) + 0.5
    else:
        xy = ((grid + 1) * size) / 2
    return sample(image, xy, method=method, a=a)
