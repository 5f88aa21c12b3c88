"""DLCTUS's trunk (four residual blocks of two edge-padded 3x3 32->32 convolutions, ReLU
between, the block's input added back) in three forms that give the same values:

- ``trunk_xla``: XLA's convolution op (cuDNN on a GPU, oneDNN/Eigen on a CPU).
- ``trunk_im2col``: each convolution as one matrix product of the nine shifted views of
  the edge-padded input, concatenated along channels (``[N, 9C] @ [9C, C]``). A 3x3
  convolution with 32 channels is too narrow for cuDNN to run near a GPU's peak; a
  matmul with a 288-deep contraction is a plain GEMM XLA hands to cuBLAS or Triton.
- ``trunk_pallas``: one Pallas (Triton) kernel per convolution. Each program computes a
  ``TILE`` of output pixels: nine loads of the tile's shifted window, with row and
  column indices clamped to the image (the edge padding, with no padded copy), nine
  ``[pixels, C] @ [C, C]`` products accumulated in float32 whatever the compute dtype,
  then the bias and the ReLU or the residual add in the same kernel. The activations
  between convolutions keep a layout rounded up to whole tiles (the clamped indices
  never read the rounding), so the trunk pads once and crops once.

Why not the whole trunk in one kernel per tile with halos: Pallas's Triton lowering
needs every array in a kernel to have power-of-two sizes and cannot slice a value, so
the halo cannot shrink layer by layer. A 32x32 tile with the eight-pixel halo would
compute every convolution on 1,024 positions to keep 256 (4x the FLOPs), and shifting
an activation would go through memory anyway. Pallas's default GPU back end on JAX
0.10 (Mosaic GPU) stages whole blocks in shared memory (232 KB on a Hopper), which an
image does not fit; the kernel names the Triton back end.

``trunk(params, h, blocks, kernels)`` picks the form; ``"pallas"`` has the XLA trunk's
gradients (a custom VJP whose backward differentiates ``trunk_xla``). On a CPU the
kernel runs in Pallas's interpret mode: the tests check it there against the XLA path,
to 1e-5 in float32. ``dlctus.Config(kernels=...)`` selects the form; XLA's stays the
default wherever another is not measured faster (docs/performance.md).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pltriton

from jtus.models import layers
from jtus.sampling import pad_edge

# output pixels per program (rows, columns; powers of two for Triton) and warps per
# program: the fastest of those timed on an H200 at 720p, 1080p and 4K (bfloat16;
# docs/results/gpu/trunk-forms.json)
TILE = (8, 32)
NUM_WARPS = 8


def stack_blocks(params, blocks):
    """``(w1, b1, w2, b2)``: the blocks' kernels ``[blocks,3,3,C,C]`` and biases
    ``[blocks,C]``, stacked from DLCTUS's parameter tree."""
    def get(conv, name):
        return jnp.stack([params[f"block{i + 1}"][conv][name] for i in range(blocks)])
    return get("conv1", "kernel"), get("conv1", "bias"), get("conv2", "kernel"), \
        get("conv2", "bias")


def trunk_xla(w1, b1, w2, b2, h):
    """The trunk as XLA convolutions: the reference the other forms match, and the
    Pallas form's backward."""
    for i in range(w1.shape[0]):
        r = jax.nn.relu(layers.conv_edge_fast(h, w1[i], b1[i]))
        h = h + layers.conv_edge_fast(r, w2[i], b2[i])
    return h


def conv_im2col(x, k, b):
    """Edge-padded 3x3 convolution of ``x [B,H,W,C]`` as one matmul: the nine shifted
    views of the padded input side by side (tap ``(dy, dx)`` at channels
    ``(3 dy + dx) C ...``), times the HWIO kernel read as ``[9C, O]``."""
    H, W = x.shape[1:3]
    xp = pad_edge(x, 1)
    cols = jnp.concatenate([xp[:, dy:dy + H, dx:dx + W, :] for dy in range(3)
                            for dx in range(3)], axis=-1)
    return cols @ k.reshape(-1, k.shape[-1]).astype(x.dtype) + b.astype(x.dtype)


def trunk_im2col(w1, b1, w2, b2, h):
    for i in range(w1.shape[0]):
        r = jax.nn.relu(conv_im2col(h, w1[i], b1[i]))
        h = h + conv_im2col(r, w2[i], b2[i])
    return h


def _conv_kernel(x_ref, k_ref, b_ref, *refs, tile, height, width, relu, residual):
    """One tile of ``conv(x) + bias``, then ReLU or ``+ res`` (``refs``: the residual's
    ref when ``residual``, then the output's)."""
    o_ref = refs[-1]
    bi, ty, tx = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    th, tw = tile
    c = x_ref.shape[-1]
    ys = ty * th + jax.lax.broadcasted_iota(jnp.int32, (th, 1), 0)
    xs = tx * tw + jax.lax.broadcasted_iota(jnp.int32, (1, tw), 1)
    acc = jnp.zeros((th * tw, k_ref.shape[-1]), jnp.float32)
    for dy in range(3):
        rows = jnp.clip(ys + (dy - 1), 0, height - 1)
        for dx in range(3):
            cols = jnp.clip(xs + (dx - 1), 0, width - 1)
            patch = x_ref[bi, rows, cols, :].reshape(th * tw, c)
            acc = acc + jnp.dot(patch, k_ref[dy, dx, :, :], preferred_element_type=jnp.float32)
    acc = acc + b_ref[...].astype(jnp.float32)[None, :]
    if relu:
        acc = jnp.maximum(acc, 0.0)
    out = acc.reshape(th, tw, -1)
    if residual:
        out = out + refs[0][bi, pl.ds(ty * th, th), pl.ds(tx * tw, tw), :].astype(jnp.float32)
    o_ref[0] = out.astype(o_ref.dtype)


def conv_pallas(x, k, b, size, relu=False, res=None, tile=TILE, num_warps=NUM_WARPS,
                interpret=False):
    """Edge-padded 3x3 convolution of the image ``size = (H, W)`` held at the top left
    of ``x [B, H', W', C]`` (``H' W'`` whole tiles), with ReLU or ``+ res`` fused; the
    output has ``x``'s layout (what lies past ``size`` is not meaningful)."""
    B, Hp, Wp, _ = x.shape
    th, tw = tile
    grid = (B, Hp // th, Wp // tw)
    full = lambda a: pl.BlockSpec(a.shape, lambda *_: (0,) * a.ndim)  # noqa: E731
    ins = [x, k.astype(x.dtype), b.astype(x.dtype)] + ([] if res is None else [res])
    kernel = functools.partial(_conv_kernel, tile=tile, height=size[0], width=size[1],
                               relu=relu, residual=res is not None)
    return pl.pallas_call(
        kernel,
        out_shape=jax.ShapeDtypeStruct((B, Hp, Wp, k.shape[-1]), x.dtype),
        grid=grid,
        in_specs=[full(a) for a in ins],
        out_specs=pl.BlockSpec((1, th, tw, k.shape[-1]), lambda i, j, m: (i, j, m, 0)),
        interpret=interpret,
        compiler_params=None if interpret else pltriton.CompilerParams(num_warps=num_warps),
        name=f"jtus_conv3x3{'_relu' if relu else ''}{'_res' if res is not None else ''}",
    )(*ins)


def trunk_pallas(w1, b1, w2, b2, h, tile=TILE, num_warps=NUM_WARPS, interpret=False):
    """The trunk on ``h [B,H,W,C]`` (the stacked weights of ``stack_blocks``), eight
    ``conv_pallas`` calls on a layout rounded up to whole tiles."""
    B, H, W, C = h.shape
    th, tw = tile
    x = jnp.pad(h, ((0, 0), (0, -H % th), (0, -W % tw), (0, 0)), mode="edge")
    for i in range(w1.shape[0]):
        opts = dict(tile=tile, num_warps=num_warps, interpret=interpret)
        r = conv_pallas(x, w1[i], b1[i], (H, W), relu=True, **opts)
        x = conv_pallas(r, w2[i], b2[i], (H, W), res=x, **opts)
    return x[:, :H, :W, :]


@functools.partial(jax.custom_vjp, nondiff_argnums=(5,))
def _trunk(w1, b1, w2, b2, h, interpret):
    return trunk_pallas(w1, b1, w2, b2, h, interpret=interpret)


def _trunk_fwd(w1, b1, w2, b2, h, interpret):
    return trunk_pallas(w1, b1, w2, b2, h, interpret=interpret), (w1, b1, w2, b2, h)


def _trunk_bwd(interpret, res, g):
    _, vjp = jax.vjp(trunk_xla, *res)
    return vjp(g)


_trunk.defvjp(_trunk_fwd, _trunk_bwd)


def trunk(params, h, blocks, kernels="pallas", interpret=None):
    """DLCTUS's trunk on ``h [B,H/4,W/4,C]`` in the form ``kernels`` names (``"xla"``,
    ``"im2col"`` or ``"pallas"``); ``interpret`` None: Pallas's interpret mode on a CPU
    backend, compiled elsewhere."""
    args = stack_blocks(params, blocks)
    if kernels == "xla":
        return trunk_xla(*args, h)
    if kernels == "im2col":
        return trunk_im2col(*args, h)
    if interpret is None:
        interpret = jax.default_backend() == "cpu"
    return _trunk(*args, h, interpret)
