"""A fused Pallas kernel for DLCTUS's trunk: its residual blocks (two 3x3 edge-padded
convolutions each, ReLU between, the block's input added back) in one kernel per tile.

Each program of the grid ``(batch, tile rows, tile columns)`` reads its tile of the
trunk's input with a halo of one pixel per convolution (8 for four blocks), runs every
block on it, and writes the tile. Each 3x3 convolution is nine matrix products of the
tile's shifted views with the tap's 32x32 kernel, accumulated in float32 whatever the
compute dtype, and shrinks the tile by a pixel on each side; the residual adds the
input cropped to match. At the image's border the convolutions must see edge-padded
activations at every layer, not only at the input: after each layer, the positions of
the tile that lie outside the image take the value of the image's edge row (then
column), picked by a masked sum so that the kernel needs no gather. Positions inside
the image never read a value the halo does not hold, so the tile's centre is exact.

``trunk(params, h, config, interpret)`` has the XLA trunk's gradients (a custom VJP
whose backward differentiates ``trunk_xla``). On a CPU the kernel runs in Pallas's
interpret mode: the tests check it there against the XLA path, to 1e-5 in float32.
``dlctus.Config(kernels="pallas")`` selects it; XLA stays the default until the kernel
is measured faster on a GPU (docs/performance.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from jtus.models import layers

TILE = 16  # output pixels per tile side (before rounding to the image)


def stack_blocks(params, blocks):
    """``(w1, b1, w2, b2)``: the blocks' kernels ``[blocks,3,3,C,C]`` and biases
    ``[blocks,C]``, stacked from DLCTUS's parameter tree."""
    def get(conv, name):
        return jnp.stack([params[f"block{i + 1}"][conv][name] for i in range(blocks)])
    return get("conv1", "kernel"), get("conv1", "bias"), get("conv2", "kernel"), \
        get("conv2", "bias")


def trunk_xla(w1, b1, w2, b2, h):
    """The trunk as XLA ops: the reference the kernel matches, and its backward."""
    for i in range(w1.shape[0]):
        r = jax.nn.relu(layers.conv_edge_fast(h, w1[i], b1[i]))
        h = h + layers.conv_edge_fast(r, w2[i], b2[i])
    return h


def _conv_valid(h, k, b):
    """3x3 VALID convolution of a tile ``[S,S',C]`` as nine matmuls, float32 sums."""
    s0, s1, c = h.shape[0] - 2, h.shape[1] - 2, h.shape[2]
    out = jnp.zeros((s0 * s1, k.shape[-1]), jnp.float32)
    for dy in range(3):
        for dx in range(3):
            patch = h[dy:dy + s0, dx:dx + s1, :].reshape(s0 * s1, c)
            out = out + jnp.dot(patch, k[dy, dx], preferred_element_type=jnp.float32)
    return (out + b.astype(jnp.float32)).reshape(s0, s1, -1)


def _edge_fix(h, row0, col0, height, width):
    """Positions of the tile outside the image take the image's edge value (rows,
    then columns, so corners take the corner). ``row0, col0``: the image coordinates
    of the tile's first row and column."""
    rows = row0 + jax.lax.broadcasted_iota(jnp.int32, h.shape, 0)
    cols = col0 + jax.lax.broadcasted_iota(jnp.int32, h.shape, 1)
    zero = jnp.zeros_like(h)
    top = jnp.sum(jnp.where(rows == 0, h, zero), axis=0, keepdims=True)
    bottom = jnp.sum(jnp.where(rows == height - 1, h, zero), axis=0, keepdims=True)
    h = jnp.where(rows < 0, top, jnp.where(rows > height - 1, bottom, h))
    left = jnp.sum(jnp.where(cols == 0, h, zero), axis=1, keepdims=True)
    right = jnp.sum(jnp.where(cols == width - 1, h, zero), axis=1, keepdims=True)
    return jnp.where(cols < 0, left, jnp.where(cols > width - 1, right, h))


def _kernel(x_ref, w1_ref, b1_ref, w2_ref, b2_ref, o_ref, *, tile, height, width, blocks):
    halo = 2 * blocks
    ty, tx = pl.program_id(1), pl.program_id(2)
    th, tw = tile
    h = x_ref[pl.program_id(0), pl.ds(ty * th, th + 2 * halo), pl.ds(tx * tw, tw + 2 * halo), :]
    dt = h.dtype
    r0, c0 = ty * th - halo, tx * tw - halo
    for i in range(blocks):
        r = jax.nn.relu(_conv_valid(h, w1_ref[i], b1_ref[i])).astype(dt)
        r = _edge_fix(r, r0 + 2 * i + 1, c0 + 2 * i + 1, height, width)
        h = (h[2:-2, 2:-2, :].astype(jnp.float32)
             + _conv_valid(r, w2_ref[i], b2_ref[i])).astype(dt)
        h = _edge_fix(h, r0 + 2 * i + 2, c0 + 2 * i + 2, height, width)
    o_ref[0] = h


def _tile(n):
    """A tile side for ``n`` pixels: ``TILE``, or ``n`` rounded up to 8 if smaller."""
    return min(TILE, -(-n // 8) * 8)


def trunk_pallas(w1, b1, w2, b2, h, interpret=False):
    """The fused trunk on ``h [B,H,W,C]`` (the stacked weights of ``stack_blocks``)."""
    blocks = w1.shape[0]
    halo = 2 * blocks
    B, H, W, C = h.shape
    th, tw = _tile(H), _tile(W)
    ny, nx = -(-H // th), -(-W // tw)
    x = jnp.pad(h, ((0, 0), (halo, halo + ny * th - H), (halo, halo + nx * tw - W), (0, 0)),
                mode="edge")
    dt = h.dtype
    w1, b1, w2, b2 = (a.astype(dt) for a in (w1, b1, w2, b2))
    full = lambda a: pl.BlockSpec(a.shape, lambda b, i, j: (0,) * a.ndim)  # noqa: E731
    out = pl.pallas_call(
        functools.partial(_kernel, tile=(th, tw), height=H, width=W, blocks=blocks),
        out_shape=jax.ShapeDtypeStruct((B, ny * th, nx * tw, C), dt),
        grid=(B, ny, nx),
        in_specs=[full(x), full(w1), full(b1), full(w2), full(b2)],
        out_specs=pl.BlockSpec((1, th, tw, C), lambda b, i, j: (b, i, j, 0)),
        interpret=interpret,
    )(x, w1, b1, w2, b2)
    return out[:, :H, :W, :]


@functools.partial(jax.custom_vjp, nondiff_argnums=(5,))
def _trunk(w1, b1, w2, b2, h, interpret):
    return trunk_pallas(w1, b1, w2, b2, h, interpret)


def _trunk_fwd(w1, b1, w2, b2, h, interpret):
    return trunk_pallas(w1, b1, w2, b2, h, interpret), (w1, b1, w2, b2, h)


def _trunk_bwd(interpret, res, g):
    _, vjp = jax.vjp(trunk_xla, *res)
    return vjp(g)


_trunk.defvjp(_trunk_fwd, _trunk_bwd)


def trunk(params, h, blocks, interpret=None):
    """DLCTUS's trunk on ``h [B,H/4,W/4,C]`` through the fused kernel; ``interpret``
    None: Pallas's interpret mode on a CPU backend, compiled elsewhere."""
    if interpret is None:
        interpret = jax.default_backend() == "cpu"
    return _trunk(*stack_blocks(params, blocks), h, interpret)
