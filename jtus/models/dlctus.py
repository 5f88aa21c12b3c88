"""DLCTUS: Deep Learning Controlled Temporal Upsampling (thesis sec. 4.1, eq. 44-46).

A step, for up-sampling factor f and an HR frame of ``H x W = f*h x f*w``:

1. input up-sampling: RGB and linear depth zero-up-sampled (``zero [B,H,W,4]``);
   RGB with a fourth channel of ones jitter-aligned up-sampled, bilinear (``jau``);
2. history reprojection: motion vectors up-sampled bilinearly (optionally 3x3-dilated
   first), the history ``[B,H,W,4]`` read at ``P + f*mv`` with the configured warp,
   and replaced by ``jau`` where that falls outside the previous frame;
3. the network on ``concat(zero, hist)`` (8 channels): 4x4 stride-4 convolution to
   32 channels, four residual blocks (3x3 edge-padded conv, ReLU, 3x3 conv, add),
   pixel shuffle by 4 to 2 channels ``o``, clamped to [0,1];
4. output construction: ``out = jau * o1 + hist * (1 - o1)`` on all four channels,
   the accumulation channel multiplied by ``o2``, all clamped to [0,1]. ``out`` is the
   new history; its RGB is the frame's output.

Formulations (thesis sec. 4.4.4), equal up to float rounding: ``standard``; ``opt1``
(no pixel-shuffle layer: output construction runs on space-to-depth tensors and one
shuffle writes the result); ``opt2`` (the 4x4 stride-4 convolution as space-to-depth
followed by a 1x1 convolution, i.e. a matmul).

Without the accumulation buffer the history's fourth channel is held at 1: the
network still sees 8 channels and ``o2`` is unused.

``resample_input`` (a variant, not the thesis's model) gives the network a ninth
channel after the history, ``resample_offset``: how far the history read lies from a
pixel centre. ``adapt_params`` grows 8-input weights for it with zero rows.

In training, the 4x4 down-sampling and the output construction are recomputed in the
backward pass (``remat_edges``, ``jax.checkpoint``): a training scan would otherwise
stack their residuals (the history in two layouts, the blend's masks and factors) for
every frame, which on XLA:CPU costs more than the recomputation (docs/performance.md,
"The scan's buffers"). Values are the same either way.

Preparation and output construction run in float32; the network in the configured
compute dtype; the carried history is always float32 (all three are float64 when
``dtype="float64"``, for references and gradient checks).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import pickle
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jtus import sampling
from jtus.data.conventions import FAR, NEAR, linearize_depth
from jtus.frame import Frame
from jtus.models import dlctus_onnx, kernels, layers
from jtus.models.base import (Cost, ExportIO, Model, Spec, bind, carry_dtype, compute_dtype,
                              reset_select)

FORMULATIONS = ("standard", "opt1", "opt2")
# the trunk's forms (jtus.models.kernels); "auto" picks by measurement (Config.trunk_form)
KERNELS = ("auto", "xla", "im2col", "pallas")
DOWN = 4  # the network works at 1/4 of the HR resolution
# the trunk maps (batch x height x width on a device, smallest and largest) that
# conv_backward="auto" differentiates by Winograd: the training step was faster with it
# at 2 x 32 x 32 and 2 x 64 x 64 (crops 128 and 256, split over two devices), slower at
# 4 x 16 x 16 (crop 64, one device) and 2 x 128 x 128 (crop 512; docs/performance.md)
WINOGRAD_PIXELS = (2 * 32 * 32, 2 * 64 * 64)


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    near: float = NEAR
    far: float = FAR
    warp: str = "bicubic"        # any jtus.sampling method
    warp_a: float = -0.75        # Keys parameter of the cubic warps (PyTorch's)
    accumulation: bool = True
    dilation: bool = False
    dtype: str = "float32"       # network compute dtype; the history stays float32
    # The fastest on XLA:CPU by measurement (docs/performance.md); every formulation
    # and backward gives the same values (Winograd's to float32 rounding, and only under
    # differentiation), so they change speed only.
    formulation: str = "opt2"
    # how the trunk's convolutions are differentiated: "custom" (layers.conv_edge_fast),
    # "winograd" (layers.conv_edge_winograd), "autodiff"; "auto": Config.conv_form
    conv_backward: str = "auto"
    kernels: str = "auto"        # "xla", "im2col" (matmuls), "pallas" (Triton kernels)
    # recompute the 4x4 down-sampling and the output construction in the backward pass
    # rather than keep their residuals per frame (a training scan stacks them)
    remat_edges: bool = True
    channels: int = 32
    blocks: int = 4
    # A variant, not the thesis's model: one more input channel, how far the history
    # read lies from a pixel centre (``resample_offset``), 0 where the history is read
    # exactly (a still pixel) and up to 1 where the bicubic read blurs it most; the
    # blend can then keep a long memory where the history is exact
    resample_input: bool = False

    def __post_init__(self):
        if self.factor not in (2, 4):
            raise ValueError(f"factor: expected 2 or 4, got {self.factor}")
        if not 0 < self.near < self.far:
            raise ValueError(f"near/far: expected 0 < near < far, got {self.near}, {self.far}")
        if self.warp not in sampling.METHODS:
            raise ValueError(f"warp: expected one of {sampling.METHODS}, got {self.warp!r}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation: expected one of {FORMULATIONS}, "
                             f"got {self.formulation!r}")
        if self.channels != 2 * DOWN * DOWN:
            raise ValueError(f"channels: the pixel shuffle to 2 outputs needs "
                             f"{2 * DOWN * DOWN}, got {self.channels}")
        if self.conv_backward not in layers.CONV_BACKWARDS:
            raise ValueError(f"conv_backward: expected one of {layers.CONV_BACKWARDS}, "
                             f"got {self.conv_backward!r}")
        if self.kernels not in KERNELS:
            raise ValueError(f"kernels: expected one of {KERNELS}, got {self.kernels!r}")
        compute_dtype(self.dtype)

    @property
    def in_channels(self):
        """The network's input channels: eq. 46's 8, 9 with ``resample_input``."""
        return 8 + int(self.resample_input)

    def conv_form(self, backend=None, pixels=None):
        """How the trunk's convolutions are differentiated on ``backend`` (JAX's default if
        None) for maps of ``pixels`` (batch x height x width on one device; None: any):
        ``conv_backward``, or for ``"auto"`` Winograd's F(4x4, 3x3) forward and input
        gradient on a CPU in float32 or float64 within ``WINOGRAD_PIXELS``, where it was
        measured faster in the training step (docs/performance.md), and ``"custom"``
        elsewhere (smaller maps, where its many small operations cost more than they save;
        larger ones, whose transformed tiles outgrow the cache; bfloat16, whose rounding
        F(4x4)'s transforms would amplify; GPUs, where it was not measured).
        Without differentiation every form is ``layers.conv_edge``."""
        if self.conv_backward != "auto":
            return self.conv_backward
        cpu = (backend or jax.default_backend()) == "cpu"
        lo, hi = WINOGRAD_PIXELS
        fits = pixels is None or lo <= pixels <= hi
        return "winograd" if cpu and fits and self.dtype in ("float32", "float64") else "custom"

    def train_conv_form(self, batch, crop, backend=None):
        """The trunk's form in a training step on ``batch`` crops of ``crop`` HR pixels
        per device (``python -m jtus.bench`` records it)."""
        return self.conv_form(backend, batch * (crop // DOWN) ** 2)

    def trunk_form(self, backend=None):
        """The trunk's form on ``backend`` (JAX's default if None): ``kernels``, or for
        ``"auto"`` the Pallas kernels on a GPU in bfloat16, the one case where they were
        measured faster than XLA's convolutions at every size and factor (an H200,
        docs/performance.md), and XLA's everywhere else (float32 on a GPU, where XLA
        uses TF32 and the kernels full float32; every CPU, where Pallas interprets)."""
        if self.kernels != "auto":
            return self.kernels
        gpu = (backend or jax.default_backend()) in ("gpu", "cuda")
        return "pallas" if gpu and self.dtype == "bfloat16" else "xla"


class State(NamedTuple):
    history: jax.Array  # [B,H,W,4] float32: RGB and accumulation


def init(key, config: Config = Config()):
    """Parameters with PyTorch's default initialization (kernels HWIO)."""
    keys = jax.random.split(key, 1 + 2 * config.blocks)
    c = config.channels
    params = {"down": layers.torch_uniform_init(keys[0], (DOWN, DOWN, config.in_channels, c))}
    for i in range(config.blocks):
        params[f"block{i + 1}"] = {
            "conv1": layers.torch_uniform_init(keys[1 + 2 * i], (3, 3, c, c)),
            "conv2": layers.torch_uniform_init(keys[2 + 2 * i], (3, 3, c, c)),
        }
    return params


def adapt_params(params, config: Config = Config()):
    """Parameters of the thesis's 8-input network grown to ``config``'s inputs: the
    ``resample_input`` channel's kernel rows are zero, so the grown network computes
    what the given one does until training moves them. Parameters that already fit
    are returned as they are."""
    k = params["down"]["kernel"]
    have, want = k.shape[2], config.in_channels
    if have == want:
        return params
    if have != 8 or want < have:
        raise ValueError(f"params: down kernel with {have} input channels, this config "
                         f"takes {want}")
    grown = jnp.concatenate([k, jnp.zeros(k.shape[:2] + (want - have, k.shape[3]), k.dtype)],
                            axis=2)
    return {**params, "down": {**params["down"], "kernel": grown}}


def resample_offset(motion, factor):
    """``[B,H,W,1]``: how far each HR pixel's history read (at ``P + f * mv``, mv
    up-sampled bilinearly) lies from a pixel centre, ``|dx - round(dx)| + |dy -
    round(dy)|`` in [0, 1]: 0 where the read is exact, as on a still pixel."""
    d = factor * sampling.upsample(motion, factor)
    return jnp.sum(jnp.abs(d - jnp.round(d)), axis=-1, keepdims=True)


def _cast(frame, config):
    dt = carry_dtype(config.dtype)
    return tuple(x.astype(dt) for x in (frame.color, frame.depth, frame.motion, frame.jitter))


def _jau(config, color, jitter):
    ones = jnp.ones(color.shape[:-1] + (1,), color.dtype)
    return sampling.jitter_aligned_upsample(jnp.concatenate([color, ones], -1), jitter,
                                            config.factor, "bilinear")


def init_state(frame: Frame, config: Config = Config()) -> State:
    """The history of a sequence's first frame: its jitter-aligned input, accumulation 1."""
    color, _, _, jitter = _cast(frame, config)
    return State(_jau(config, color, jitter))


def _trunk(params, h, config):
    form = config.trunk_form()
    if form != "xla":
        return kernels.trunk(params, h, config.blocks, form)
    conv = {"custom": layers.conv_edge_fast, "winograd": layers.conv_edge_winograd,
            "autodiff": layers.conv_edge}[config.conv_form(pixels=math.prod(h.shape[:3]))]
    for i in range(config.blocks):
        blk = params[f"block{i + 1}"]
        r = jax.nn.relu(conv(h, blk["conv1"]["kernel"], blk["conv1"]["bias"]))
        h = h + conv(r, blk["conv2"]["kernel"], blk["conv2"]["bias"])
    return h


class NetInput(NamedTuple):
    """The network's input before assembly: ``concat(zero_upsample(lr), hist)``."""
    lr: jax.Array      # [B,h,w,4] RGB and linear depth, low resolution
    jitter: jax.Array  # [B,2]
    hist: jax.Array    # [B,H,W,4] the reprojected history
    offset: Optional[jax.Array] = None  # [B,H,W,1] ``resample_offset`` (resample_input)


def _hist_part(x: NetInput):
    """The HR half of the input: the history, and the resample offset when given."""
    return x.hist if x.offset is None else jnp.concatenate(
        [x.hist, x.offset.astype(x.hist.dtype)], -1)


def assemble(x: NetInput, config: Config):
    """The dense network input ``[B,H,W,8]`` (eq. 46's input; 9 channels with the
    resample offset)."""
    zero = sampling.zero_upsample(x.lr, x.jitter, config.factor)
    return jnp.concatenate([zero, _hist_part(x).astype(zero.dtype)], -1)


def _down(params, x: NetInput, config, dt):
    k, b = params["down"]["kernel"], params["down"]["bias"]
    if config.formulation != "opt2":
        return layers.conv(assemble(x, config).astype(dt), k, b, stride=DOWN, padding="VALID")
    # opt2: space-to-depth then a matmul, with the zero-up-sampled half never built.
    # In a 4x4 block the zero-up-sampled image is non-zero only at the sub-pixels the
    # LR samples land on (row f*a + cell_y, column f*b + cell_x, for the m x m LR pixels
    # of the block, m = 4 / f), so its product with the kernel is the LR image,
    # space-to-depth by m, times the kernel rows of those sub-pixels (chosen per frame
    # from the jitter). The history half is space-to-depth by 4 times its kernel rows.
    f, m = config.factor, DOWN // config.factor
    nb, c_lr = x.lr.shape[0], x.lr.shape[-1]
    cell = sampling.jitter_cell(x.jitter, f)                     # [B,2] (x, y)
    rows = f * jnp.arange(m)
    dy, dx = rows[None, :] + cell[:, 1:2], rows[None, :] + cell[:, 0:1]   # [B,m]
    k_lr = jnp.asarray(k)[dy[:, :, None], dx[:, None, :], :c_lr]              # [B,m,m,c,O]
    k_lr = k_lr.transpose(0, 3, 1, 2, 4).reshape(nb, c_lr * m * m, -1)  # row c*m*m + a*m + b
    lr = sampling.pixel_unshuffle(x.lr, m) if m > 1 else x.lr
    zero_part = jnp.einsum("bhwk,bko->bhwo", lr.astype(dt), k_lr.astype(dt))
    k_h = k[:, :, c_lr:].transpose(2, 0, 1, 3).reshape(-1, k.shape[-1])  # (c, dy, dx)
    hist_part = sampling.pixel_unshuffle(_hist_part(x).astype(dt), DOWN) @ k_h.astype(dt)
    return zero_part + hist_part + b.astype(dt)


def _edge(fn, config: Config):
    """``fn``, recomputed in the backward pass when ``config.remat_edges``: a training
    scan then stacks none of its residuals (docs/performance.md, "The scan's buffers")."""
    return jax.checkpoint(fn) if config.remat_edges else fn


def network(params, x: NetInput, config: Config):
    """The network on ``concat(zero_upsample(x.lr), x.hist)`` -> ``[B,H/4,W/4,32]`` in
    the compute dtype (before the shuffle)."""
    dt = compute_dtype(config.dtype)
    params = jax.tree_util.tree_map(lambda p: p.astype(dt), params)
    down = _edge(functools.partial(_down, config=config, dt=dt), config)
    return _trunk(params, down(params, x), config)


def _construct(jau, hist, o1, o2, config, axis):
    """Eq. 44-45. ``axis`` is the axis of the 4 history channels (RGB, accumulation);
    ``o1``, ``o2`` broadcast against ``jau`` with size 1 on it."""
    out = jau * o1 + hist * (1 - o1)
    if config.accumulation:
        rgb, acc = jnp.split(out, [3], axis=axis)
        out = jnp.concatenate([rgb, acc * o2], axis=axis)
    return jnp.clip(out, 0.0, 1.0)


def output(jau, hist, net, config):
    """Stage 4, eq. 44-45: the new history ``[B,H,W,4]`` from the jitter-aligned input
    ``jau``, the reprojected history ``hist`` and the network's output ``net`` (before the
    shuffle; clamped to [0,1] here)."""
    net = jnp.clip(net.astype(jau.dtype), 0.0, 1.0)
    if config.formulation == "opt1":
        # Stay in space-to-depth layout [B,H/4,W/4,channel,sub-pixel]; shuffle once.
        b, hh, ww, _ = net.shape
        s = DOWN * DOWN
        o = net.reshape(b, hh, ww, 2, s)
        j = sampling.pixel_unshuffle(jau, DOWN).reshape(b, hh, ww, 4, s)
        hs = sampling.pixel_unshuffle(hist, DOWN).reshape(b, hh, ww, 4, s)
        out = _construct(j, hs, o[..., 0:1, :], o[..., 1:2, :], config, axis=-2)
        return sampling.pixel_shuffle(out.reshape(b, hh, ww, 4 * s), DOWN)
    o = sampling.pixel_shuffle(net, DOWN)
    return _construct(jau, hist, o[..., 0:1], o[..., 1:2], config, axis=-1)


class Prepared(NamedTuple):
    """What a step needs of its frame that does not depend on the history (stages 1
    and the coordinate half of 2): computed for every frame of a sequence at once,
    outside the recurrent scan (``Model.prepare``), so the scan carries only what
    truly recurs and the backward pass keeps none of it per frame."""
    lr: jax.Array                 # [B,h,w,4] RGB and linear depth
    jitter: jax.Array             # [B,2]
    jau: jax.Array                # [B,H,W,4] jitter-aligned input, accumulation 1
    warp: sampling.WarpPlan       # the history read at P + f * mv
    reset: Optional[jax.Array]    # [B] bool or None
    offset: Optional[jax.Array] = None  # [B,H,W,1] ``resample_offset`` (resample_input)


def prepare_frame(frame: Frame, config: Config = Config()) -> Prepared:
    f = config.factor
    color, depth, motion, jitter = _cast(frame, config)
    # The named scopes label the HLO for profiles (python -m jtus.profile).
    with jax.named_scope("input_upsampling"):
        lr = jnp.concatenate([color, linearize_depth(depth, config.near, config.far)], -1)
        jau = _jau(config, color, jitter)
    with jax.named_scope("reprojection"):
        mv = sampling.dilate_motion(motion, depth) if config.dilation else motion
        plan = sampling.reproject_plan(mv, f, method=config.warp, a=config.warp_a,
                                       dtype=jau.dtype)
        offset = resample_offset(mv, f) if config.resample_input else None
    return Prepared(lr, jitter, jau, plan, frame.reset, offset)


def reproject(state: State, pre: Prepared, config: Config):
    """Stage 2's history half: ``(NetInput, jau, hist)``, float32; the zero-up-sampled
    half of the network input is built (or not: ``opt2``) by ``network``."""
    with jax.named_scope("reprojection"):
        history = state.history
        if not config.accumulation:
            history = history.at[..., 3].set(1.0)
        rep = sampling.warp_read(history, pre.warp, config.warp, config.warp_a)
        hist = jnp.where(pre.warp.inside, rep, pre.jau)
        # A reset (first frame, camera cut) takes the fresh input as its history, not
        # reprojected: this frame's motion points into a frame the history never saw
        # (the thesis's listing treats the first frame the same way).
        hist = reset_select(pre.reset, pre.jau, hist)
    return NetInput(pre.lr, pre.jitter, hist, pre.offset), pre.jau, hist


def advance(params, state: State, pre: Prepared, config: Config = Config()):
    """The step on a prepared frame: ``step(p, s, f) == advance(p, s, prepare_frame(f))``."""
    net_in, jau, hist = reproject(state, pre, config)
    with jax.named_scope("network"):
        net = network(params, net_in, config)
    with jax.named_scope("output"):
        out = _edge(functools.partial(output, config=config), config)(jau, hist, net)
    return out[..., :3], State(out)


def step(params, state: State, frame: Frame, config: Config = Config()):
    return advance(params, state, prepare_frame(frame, config), config)


def make(config: Config = Config()) -> Model:
    return bind(config, step, init=init, init_state=init_state, prepare=prepare_frame,
                advance=advance)


def cost(config: Config, H, W) -> Cost:
    """FLOPs and bytes of one H x W output frame (``jtus.cost``)."""
    n = (H // 4) * (W // 4)
    c = config.channels
    down = n * c * (4 * 4 * config.in_channels) * 2
    convs = 2 * config.blocks * n * c * c * 9 * 2
    net = down + convs + n * c * config.blocks * 3  # bias, ReLU, residual add
    px = H * W
    warp = sampling.TAPS[config.warp] * 4 * 2 + 20  # 4 channels, plus the tap weights
    prep = px * (warp + 4 * 4 * 2 + 2 * 4 * 2 + 8)  # JAU, motion up-sampling, zero-up
    out = px * 4 * 4  # eq. 44-45 and clamps
    lr = px // (config.factor ** 2)
    compulsory = 4 * (lr * 6 + 2 * px * 4 + px * 3)
    act = 4 * 2 * (px * 8 + n * c * (1 + 2 * config.blocks) + px * 2)
    return Cost(net + prep + out, net, compulsory, compulsory + act)


def network_workload(params, state: State, frame: Frame, config: Config):
    """``(fn, args)``: the network alone on this frame's input, for its timing."""
    net_in, _, _ = reproject(state, prepare_frame(frame, config), config)
    return (lambda p, x: network(p, x, config)), (params, net_in)


# ---------------------------------------------------------------- PyTorch interop

def _torch_names(blocks=4):
    """(torch key, path in params) for the thesis's PyTorch module layout."""
    names = [("down.0.weight", ("down", "kernel")), ("down.0.bias", ("down", "bias"))]
    for i in range(1, blocks + 1):
        for tidx, conv in ((0, "conv1"), (2, "conv2")):
            names.append((f"cnn{i}.{tidx}.weight", (f"block{i}", conv, "kernel")))
            names.append((f"cnn{i}.{tidx}.bias", (f"block{i}", conv, "bias")))
    return names


def _to_numpy(v):
    if hasattr(v, "detach"):  # a torch tensor, converted without importing torch here
        v = v.detach().cpu().numpy()
    return np.asarray(v)


def params_from_torch(state_dict, config: Config = Config()):
    """Params from a state_dict named like the thesis's model (``down.0.weight``,
    ``cnn1.0.weight``, ... ``cnn4.2.bias``; kernels OIHW). Tensors or arrays."""
    names = _torch_names(config.blocks)
    expected = {k for k, _ in names}
    got = set(state_dict)
    if got != expected:
        missing, extra = sorted(expected - got), sorted(got - expected)
        raise ValueError(f"state_dict: keys do not match DLCTUS; missing {missing}, "
                         f"unexpected {extra}")
    ref = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), config))  # shapes only
    params = jax.tree_util.tree_map(lambda x: None, ref)
    for key, path in names:
        v = _to_numpy(state_dict[key])
        if not np.issubdtype(v.dtype, np.floating):
            raise ValueError(f"state_dict[{key!r}]: expected floating-point weights, got "
                             f"{v.dtype}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"state_dict[{key!r}]: {int(np.sum(~np.isfinite(v)))} NaN or "
                             "infinite values")
        v = v.astype(np.float32)
        if v.ndim == 4:
            v = v.transpose(2, 3, 1, 0)  # OIHW -> HWIO
        node, want = params, ref
        for p in path[:-1]:
            node, want = node[p], want[p]
        if v.shape != want[path[-1]].shape:
            raise ValueError(f"state_dict[{key!r}]: expected shape "
                             f"{_torch_shape(want[path[-1]].shape)}, got {_torch_shape(v.shape)}")
        node[path[-1]] = jnp.asarray(v)
    return params


def _torch_shape(hwio):
    return tuple(hwio[i] for i in (3, 2, 0, 1)) if len(hwio) == 4 else tuple(hwio)


def params_to_torch(params, config: Config = Config()):
    """The inverse of ``params_from_torch``: an ordered dict of torch tensors (OIHW)."""
    if config.resample_input:
        raise ValueError("resample_input: the thesis's PyTorch model has 8 input channels; "
                         "this variant's 9 have no PyTorch counterpart")
    import torch  # lazy: torch is optional, needed only to write PyTorch tensors

    out = collections.OrderedDict()
    for key, path in _torch_names(config.blocks):
        v = params
        for p in path:
            v = v[p]
        v = np.asarray(v, dtype=np.float32)
        if v.ndim == 4:
            v = v.transpose(3, 2, 0, 1)
        out[key] = torch.from_numpy(np.array(v, dtype=np.float32, order="C"))
    return out


def load_torch_checkpoint(path, config: Config = Config()):
    """Params from a ``.pt`` file: a bare state_dict or a training checkpoint dict with
    a ``model_state_dict`` entry, possibly saved from CUDA tensors and holding numpy
    scalars. Loaded on the CPU with ``weights_only=True`` and only numpy's scalar and
    dtype globals allowed: no arbitrary code is unpickled."""
    import torch  # lazy: torch is optional, needed only to read .pt files

    allowed = [np.dtype, type(np.dtype(np.float64)), type(np.dtype(np.float32)),
               type(np.dtype(np.int64)), type(np.dtype(np.int32))]
    try:
        scalar = np._core.multiarray.scalar
    except AttributeError:  # numpy < 2
        scalar = np.core.multiarray.scalar
    # The unpickler matches globals by the name in the file: numpy 1.x (the thesis's
    # released checkpoints) wrote numpy.core.multiarray.scalar, numpy 2 writes
    # numpy._core.multiarray.scalar. Both names are allowed, for the same function.
    allowed += [(scalar, "numpy.core.multiarray.scalar"),
                (scalar, "numpy._core.multiarray.scalar")]
    try:
        with torch.serialization.safe_globals(allowed):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError) as e:
        raise ValueError(f"{path}: not a loadable DLCTUS checkpoint (only tensors, dicts and "
                         f"numpy scalars are accepted): {e}") from e
    if isinstance(obj, dict) and "model_state_dict" in obj:
        obj = obj["model_state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a state_dict or a dict with 'model_state_dict', "
                         f"got {type(obj).__name__}")
    obj = {k[len("module."):] if k.startswith("module.") else k: v for k, v in obj.items()}
    return params_from_torch(obj, config)


EXPORT = ExportIO(names=("history",), shapes=lambda config, H, W: ((1, H, W, 4),),
                  to_arrays=lambda state: (state.history,), from_arrays=State,
                  onnx_graph=dlctus_onnx.build)

STAGES = ("input_upsampling", "reprojection", "network", "output")

SPECS = (Spec("dlctus", make, lambda f: Config(factor=f), cost, trainable=True, stages=STAGES,
              dtypes=("float32", "bfloat16", "float16"), formulations=FORMULATIONS, kernels=KERNELS,
              network=network_workload, torch_checkpoint=load_torch_checkpoint,
              torch_state_dict=params_to_torch, torch_reference="torch_dlctus",
              export=EXPORT, shipped=True, adapt=adapt_params),)
