"""DLCTUS's step as an ONNX graph of the operators an engine's runtime implements
natively: ``Conv`` for the network, ``GridSample`` for the history read,
``DepthToSpace`` / ``SpaceToDepth`` for the pixel shuffles, and element-wise ops for
the rest (``python -m jtus.export --format onnx``).

Every operator computes what jtus's step computes (``docs/integration.md``):

- ``GridSample`` (``align_corners=0``, ``padding_mode=border``): pixel centres at
  ``(i + 0.5) / size`` in normalized units and every tap index clamped into the image,
  as ``jtus.sampling`` does; ``mode=cubic`` is Keys' kernel with a = -0.75 (jtus's
  ``bicubic`` at ``warp_a=-0.75``), ``mode=linear`` its ``bilinear``. It reads the
  history in float64: in float32 the rounding of the normalized coordinates alone moves
  a read at x ~ 1900 by 1e-4 pixels.
- The bilinear up-samplings (the jitter-aligned input, the motion vectors) are the
  fixed 3-tap stencils of ``sampling.upsample``, with the same products and sums, so
  the reprojection coordinates are jtus's to the bit; the depth is linearized as XLA
  evaluates jtus's (one rounding of the denominator).
- The 4x4 stride-4 convolution on the zero-up-sampled input is split as jtus's ``opt2``
  does it: the history half a ``Conv`` on the history, the input half a ``MatMul`` of
  the low-resolution image (``SpaceToDepth`` at 2x) with the kernel rows of this
  frame's jitter cell, chosen by ``Gather``.
- The residual blocks: ``Pad(mode=edge)``, ``Conv`` 3x3, ``Relu``, ``Pad``, ``Conv``,
  ``Add``; the shuffle to full resolution ``DepthToSpace(mode=CRD)``, PyTorch's
  ``PixelShuffle`` order.

Inputs and outputs are NHWC, as the other export formats' (``jtus.export``), with
symbolic batch, height and width: one graph serves every size that is a multiple of 4.
Configurations another operator would be needed for (another warp, motion dilation)
are refused with the field named; ``jtus.export`` then converts jtus's own step.
"""

from __future__ import annotations

import numpy as np

from jtus.sampling.color import TONEMAP_EPSILON

DOWN = 4  # the network works at 1/4 of the output resolution (dlctus.DOWN)
OPSET = 20  # GridSample's mode "cubic" (opset 20; "bicubic" in 16-19)
_NCHW, _NHWC = [0, 3, 1, 2], [0, 2, 3, 1]


def unsupported(config):
    """Why ``config`` has no native-operator graph (``None`` if it has one)."""
    if config.warp not in ("bicubic", "bilinear"):
        return f"warp={config.warp!r} (GridSample has bilinear and Keys a=-0.75 only)"
    if config.warp == "bicubic" and config.warp_a != -0.75:
        return f"warp_a={config.warp_a} (GridSample's cubic kernel has a=-0.75)"
    if config.dilation:
        return "dilation=True (no ONNX operator for the 3x3 nearest-depth selection)"
    if config.resample_input:
        return "resample_input=True (the graph builds the thesis's 8-channel input)"
    return None


class _Graph:
    """A small builder: each call appends one node and returns its output's name."""

    def __init__(self, helper, numpy_helper):
        self.h, self.nh = helper, numpy_helper
        self.nodes, self.inits, self._n = [], [], 0

    def const(self, value, dtype=np.float32):
        self._n += 1
        name = f"c{self._n}"
        self.inits.append(self.nh.from_array(np.asarray(value, dtype), name))
        return name

    def slice(self, x, start, end, axis):
        """``x`` from ``start`` to ``end`` along ``axis`` (constants)."""
        return self("Slice", x, self.const([start], np.int64), self.const([end], np.int64),
                    self.const([axis], np.int64))

    def __call__(self, op, *inputs, out=None, **attrs):
        self._n += 1
        out = out or f"{op.lower()}{self._n}"
        self.nodes.append(self.h.make_node(op, list(inputs), [out], **attrs))
        return out


def _size64(g, x, axis):
    """``x.shape[axis]`` as a float64 tensor ``[1]``."""
    return g("Cast", g("Shape", x, start=axis, end=axis + 1), to=11)


def _pixel_centres64(g, ref):
    """``[1,2,H,W]`` float64: the centres ``i + 0.5`` (x, then y) of ``ref``'s
    ``[B,C,H,W]`` pixels."""
    axes = []
    for axis in (3, 2):  # x along the width, then y
        n = g("Shape", ref, start=axis, end=axis + 1)
        r = g("Range", g.const(0, np.int64), g("Squeeze", n), g.const(1, np.int64))
        axes.append(g("Add", g("Cast", r, to=11), g.const(0.5, np.float64)))
    x, y = axes
    one = g.const([1], np.int64)
    shape = g("Concat", one, one, g("Shape", ref, start=2, end=4), axis=0)
    xs = g("Expand", g("Reshape", x, g.const([1, 1, 1, -1], np.int64)), shape)
    ys = g("Expand", g("Reshape", y, g.const([1, 1, -1, 1], np.int64)), shape)
    return g("Concat", xs, ys, axis=1)


def _normalized64(g, xy, image):
    """Pixel coordinates ``[B,Ho,Wo,2]`` (float64) in ``image`` ``[B,C,H,W]`` ->
    GridSample's grid ``xy * 2 / (W, H) - 1`` (``align_corners=0``), in float64."""
    size = g("Concat", _size64(g, image, 3), _size64(g, image, 2), axis=0)
    return g("Sub", g("Mul", xy, g("Div", g.const(2.0, np.float64), size)),
             g.const(1.0, np.float64))


def _net(g, params, config, lr, cell, hist):
    """The network on ``concat(zero_upsample(lr), hist)`` -> ``[B,32,H/4,W/4]``."""
    f, m = config.factor, DOWN // config.factor
    k = np.asarray(params["down"]["kernel"], np.float32)          # [4,4,8,O] HWIO
    c_lr, o = 4, k.shape[-1]
    # input half: the kernel rows of each jitter cell (cy, cx), rows in SpaceToDepth's
    # channel order (dy * m + dx) * C + c; kernel tap (f*dy + cy, f*dx + cx)
    rows = np.zeros((f * f, o, c_lr * m * m), np.float32)
    for cy in range(f):
        for cx in range(f):
            for dy in range(m):
                for dx in range(m):
                    for c in range(c_lr):
                        rows[cy * f + cx, :, (dy * m + dx) * c_lr + c] = \
                            k[f * dy + cy, f * dx + cx, c]
    x = g("SpaceToDepth", lr, blocksize=m) if m > 1 else lr        # [B,C*m*m,H/4,W/4]
    flat = g("Reshape", x, g("Concat", g("Shape", x, start=0, end=2),
                             g.const([-1], np.int64), axis=0))      # [B,C*m*m,HW/16]
    kr = g("Gather", g.const(rows), cell, axis=0)                  # [B,O,C*m*m]
    zero = g("MatMul", kr, flat)                                   # [B,O,HW/16]
    zero = g("Reshape", zero, g("Concat", g("Shape", x, start=0, end=1),
                                g.const([o], np.int64), g("Shape", x, start=2, end=4),
                                axis=0))
    kh = k[:, :, c_lr:].transpose(3, 2, 0, 1)                      # OIHW, history half
    h = g("Conv", hist, g.const(kh), g.const(params["down"]["bias"]), strides=[4, 4])
    h = g("Add", h, zero)
    pads = g.const([0, 0, 1, 1, 0, 0, 1, 1], np.int64)
    for i in range(config.blocks):
        blk = params[f"block{i + 1}"]
        w1, w2 = (np.asarray(blk[c]["kernel"], np.float32).transpose(3, 2, 0, 1)
                  for c in ("conv1", "conv2"))
        r = g("Relu", g("Conv", g("Pad", h, pads, mode="edge"), g.const(w1),
                        g.const(blk["conv1"]["bias"])))
        h = g("Add", h, g("Conv", g("Pad", r, pads, mode="edge"), g.const(w2),
                          g.const(blk["conv2"]["bias"])))
    return h


def _prepare(g, config, f):
    """The step's inputs in NCHW: ``(history, lr, jau, cell, scale)``, the colour
    pre-exposed (and, ``hdr``, tone-mapped) as ``jtus.models.base.exposed_parts`` does;
    ``cell [B]`` is the jitter's sub-pixel ``cy * f + cx``."""
    color = g("Transpose", "color", perm=_NCHW)                   # [B,3,h,w]
    scale = g("Reshape", "exposure", g.const([-1, 1, 1, 1], np.int64))
    color = g("Mul", color, scale)
    if config.hdr:  # tonemap: c / (1 + max(0, max(r, g, b)))
        mx = g("Max", g("ReduceMax", color, g.const([1], np.int64), keepdims=1), g.const(0.0))
        color = g("Div", color, g("Add", mx, g.const(1.0)))
    depth = g("Transpose", "depth", perm=_NCHW)
    near, far = config.near, config.far
    # linearize_depth: (near * far / (far - d * (far - near)) - near) / (far - near), as
    # XLA:CPU evaluates jtus's: the denominator with one rounding (a fused multiply-add;
    # here in float64, then rounded), the last division as a product with the rounded
    # reciprocal. Near the far plane the map magnifies rounding ~1000x, so two
    # roundings of the denominator already move the network's input by 4e-5.
    c64 = [np.float64(np.float32(v)) for v in (far, far - near)]
    den = g("Cast", g("Sub", g.const(c64[0], np.float64),
                      g("Mul", g("Cast", depth, to=11), g.const(c64[1], np.float64))), to=1)
    z = g("Div", g.const(near * far), den)
    lin = g("Mul", g("Add", z, g.const(-near)), g.const(np.float32(1.0 / (far - near))))
    lr = g("Concat", color, lin, axis=1)                           # [B,4,h,w]
    ones = g("ConstantOfShape", g("Concat", g("Shape", color, start=0, end=1),
                                  g.const([1], np.int64), g("Shape", color, start=2),
                                  axis=0), value=_one_tensor(g))
    lr_rgb1 = g("Concat", color, ones, axis=1)
    history = g("Transpose", "history", perm=_NCHW)
    jau = _jitter_aligned(g, lr_rgb1, f)                           # [B,4,H,W]
    cell = g("Clip", g("Floor", g("Mul", "jitter", g.const(float(f)))), g.const(0.0),
             g.const(float(f - 1)))
    cell = g("Cast", g("Add", g("Mul", g.slice(cell, 1, 2, 1), g.const(float(f))),
                       g.slice(cell, 0, 1, 1)), to=7)
    cell = g("Squeeze", cell, g.const([1], np.int64))              # [B] cy * f + cx
    return history, lr, jau, cell, scale


def _phase_weights(g, j, f):
    """``[B,f,3]``: the bilinear weights of LR offsets -1, 0, 1 for each of the ``f``
    HR phases, from the jitter component ``j [B,1]`` (``sampling.upsample``'s
    ``_phase_weights`` of ``(k + 0.5) / f - j``)."""
    d = g("Sub", g.const((np.arange(f) + 0.5)[None] / f), j)      # [B,f]
    fl = g("Floor", d)
    t = g("Sub", d, fl)
    lo = g("Cast", g("Less", fl, g.const(0.0)), to=1)
    one_t, hi = g("Sub", g.const(1.0), t), g("Sub", g.const(1.0), lo)
    w = [g("Mul", one_t, lo), g("Add", g("Mul", one_t, hi), g("Mul", t, lo)), g("Mul", t, hi)]
    return g("Concat", *(g("Unsqueeze", x, g.const([2], np.int64)) for x in w), axis=2)


def _taps(g, x, axis):
    """The three shifted views ``x[k : k + n]`` (k = 0, 1, 2) along ``axis`` of an
    input padded by one on each side."""
    ends = (-2, -1, np.iinfo(np.int64).max)
    return [g.slice(x, k, e, axis) for k, e in enumerate(ends)]


def _jitter_aligned(g, lr, f):
    """``sampling.jitter_aligned_upsample(lr, jitter, f, "bilinear")`` in NCHW."""
    wx = _phase_weights(g, g.slice("jitter", 0, 1, 1), f)
    wy = _phase_weights(g, g.slice("jitter", 1, 2, 1), f)
    return _phases(g, lr, wx, wy, f)


def _upsample(g, x, f):
    """``sampling.upsample(x, f, "bilinear")`` in NCHW: the stencil of a jitter of 1/2,
    its weights computed as jtus computes them, so the result is jtus's to the bit."""
    d = (np.arange(f, dtype=np.float32) + np.float32(0.5)) / np.float32(f) - np.float32(0.5)
    fl = np.floor(d)
    t = d - fl
    lo = (fl < 0).astype(np.float32)
    w = np.stack([(1 - t) * lo, (1 - t) * (1 - lo) + t * lo, t * (1 - lo)], -1)[None]
    c = g.const(w)
    return _phases(g, x, c, c, f)


def _phases(g, lr, wx, wy, f):
    """Bilinear up-sampling by ``f`` where HR phase ``k`` reads LR offsets -1, 0, 1 with
    weights ``wx``, ``wy [B,f,3]`` (``sampling.upsample``'s ``_bilinear_phases``): a
    fixed 3-tap stencil, the edge replicated; x first, then y, in the same order of
    products and sums as jtus."""
    p = g("Pad", lr, g.const([0, 0, 1, 1, 0, 0, 1, 1], np.int64), mode="edge")
    row = None
    for k, tap in enumerate(_taps(g, p, 3)):                      # [B,C,h+2,w] each
        wk = g("Reshape", g.slice(wx, k, k + 1, 2), g.const([-1, 1, 1, 1, f], np.int64))
        term = g("Mul", g("Unsqueeze", tap, g.const([4], np.int64)), wk)
        row = term if row is None else g("Add", row, term)         # [B,C,h+2,w,f]
    row = g("Reshape", row, g.const([0, 0, 0, -1], np.int64))      # [B,C,h+2,W]
    out = None
    for k, tap in enumerate(_taps(g, row, 2)):                    # [B,C,h,W] each
        wk = g("Reshape", g.slice(wy, k, k + 1, 2), g.const([-1, 1, 1, f, 1], np.int64))
        term = g("Mul", g("Unsqueeze", tap, g.const([3], np.int64)), wk)
        out = term if out is None else g("Add", out, term)         # [B,C,h,f,W]
    width = g("Shape", row, start=3, end=4)
    return g("Reshape", out, g("Concat", g.const([0, 0, -1], np.int64), width, axis=0))


def _one_tensor(g):
    return g.nh.from_array(np.ones(1, np.float32))


def _reproject(g, config, f, history, jau):
    """The history read at ``P + f * upsample(motion)``, ``jau`` where that falls
    outside the previous frame or the frame is a reset (``dlctus.reproject``)."""
    if not config.accumulation:
        history = g("Concat", g.slice(history, 0, 3, 1), g.slice(jau, 3, 4, 1), axis=1)
    mv = _upsample(g, g("Transpose", "motion", perm=_NCHW), f)     # [B,2,H,W]
    d = g("Cast", g("Mul", mv, g.const(float(f))), to=11)           # the displacement
    # The position in float64: the pixel centre plus jtus's float32 displacement, exact
    # (jtus keeps the two apart, sampling.reproject_plan); GridSample takes normalized
    # coordinates, and in float32 their rounding alone would move a read at x ~ 1920 by
    # up to 1e-4 pixels, 1e-4 in value on a noisy image.
    xy = g("Add", _pixel_centres64(g, history), d)
    mode = "cubic" if config.warp == "bicubic" else "linear"
    grid = _normalized64(g, g("Transpose", xy, perm=_NHWC), history)
    rep = g("Cast", g("GridSample", g("Cast", history, to=11), grid, mode=mode,
                      padding_mode="border", align_corners=0), to=1)
    # sampling.offset_plan: 0 <= x <= W and 0 <= y <= H, exactly; read there unless a
    # reset
    keep = g("Not", g("Reshape", "reset", g.const([-1, 1, 1, 1], np.int64)))
    for c, axis in ((0, 3), (1, 2)):
        v = g.slice(xy, c, c + 1, 1)                              # [B,1,H,W]
        keep = g("And", keep, g("And", g("GreaterOrEqual", v, g.const(0.0, np.float64)),
                                g("LessOrEqual", v, _size64(g, history, axis))))
    return g("Where", keep, rep, jau)


def build(params, config):
    """The ``onnx.ModelProto`` of one DLCTUS step with these weights and this
    ``dlctus.Config`` (float32); ``NotImplementedError`` naming the field where the
    configuration needs an operator ONNX lacks (``unsupported``)."""
    import onnx  # lazy: optional (the export extra)
    from onnx import TensorProto, helper, numpy_helper  # lazy: as above

    why = unsupported(config)
    if why:
        raise NotImplementedError(f"no native ONNX graph for {why}")
    f = config.factor
    g = _Graph(helper, numpy_helper)
    history, lr, jau, cell, scale = _prepare(g, config, f)
    hist = _reproject(g, config, f, history, jau)
    net = _net(g, params, config, lr, cell, hist)
    o = g("DepthToSpace", g("Clip", net, g.const(0.0), g.const(1.0)), blocksize=4,
          mode="CRD")                                              # [B,2,H,W]
    o1 = g.slice(o, 0, 1, 1)
    out = g("Add", g("Mul", jau, o1), g("Mul", hist, g("Sub", g.const(1.0), o1)))
    if config.accumulation:
        o2 = g.slice(o, 1, 2, 1)
        rgb = g.slice(out, 0, 3, 1)
        acc = g.slice(out, 3, 4, 1)
        out = g("Concat", rgb, g("Mul", acc, o2), axis=1)
    out = g("Clip", out, g.const(0.0), g.const(1.0))
    g("Transpose", out, perm=_NHWC, out="history_out")
    rgb = g.slice(out, 0, 3, 1)
    if config.hdr:  # inverse tonemap: t / max(epsilon, 1 - max(r, g, b))
        mx = g("ReduceMax", rgb, g.const([1], np.int64), keepdims=1)
        rgb = g("Div", rgb, g("Max", g("Sub", g.const(1.0), mx), g.const(TONEMAP_EPSILON)))
    rgb = g("Div", rgb, scale)
    g("Transpose", rgb, perm=_NHWC, out="frame")
    return onnx.helper.make_model(
        helper.make_graph(g.nodes, f"dlctus_x{f}_step", _inputs(helper, TensorProto),
                          [helper.make_tensor_value_info("frame", TensorProto.FLOAT,
                                                         ["batch", "H", "W", 3]),
                           helper.make_tensor_value_info("history_out", TensorProto.FLOAT,
                                                         ["batch", "H", "W", 4])],
                          initializer=g.inits),
        opset_imports=[helper.make_opsetid("", OPSET)], producer_name="jtus")


def _inputs(helper, tp):
    v = helper.make_tensor_value_info
    return [v("color", tp.FLOAT, ["batch", "h", "w", 3]),
            v("depth", tp.FLOAT, ["batch", "h", "w", 1]),
            v("motion", tp.FLOAT, ["batch", "h", "w", 2]),
            v("jitter", tp.FLOAT, ["batch", 2]), v("exposure", tp.FLOAT, ["batch"]),
            v("reset", tp.BOOL, ["batch"]), v("history", tp.FLOAT, ["batch", "H", "W", 4])]
