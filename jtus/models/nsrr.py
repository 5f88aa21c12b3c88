"""NSRR: Neural Supersampling for Real-time Rendering (Xiao et al. 2020, sec. 3.2-3.4).

Per frame, with up-sampling factor f and ``frames`` previous frames (4 in the paper):

1. feature extraction at LR: a 3-layer 3x3 network maps RGB-D to 8 learned features,
   concatenated with RGB-D (12 channels); the current frame has its own network, the
   previous frames share another (run on each frame when it is current and kept);
2. zero-up-sampling of the 12 channels to HR; the previous frames' zero-up-sampled
   features travel in the state and are backward-warped, bilinearly with zero padding,
   by the current frame's up-sampled motion: iterated frame after frame, each previous
   frame reaches the current one through every motion field in between;
3. feature reweighting: a 3-layer network on the current RGB-D and the warped previous
   RGB-D gives one map per previous frame, ``10 * (tanh + 1) / 2`` in [0, 10], which
   scales all 12 features of that frame;
4. reconstruction: a 3-scale, 10-layer U-Net (max-pooling down, bilinear up, skip
   concatenations) on the current and reweighted previous features gives RGB (or YCbCr
   when ``ycbcr``, converted back).

With ``exposure="normalized"`` every colour the networks read is divided by its frame's
mean LR colour (``base.exposure_normalizer``) and the output is multiplied by the
current frame's: the weights then see every level at one exposure, and a video scaled
by ``s`` gives outputs scaled by ``s``. The U-Net builds its output from scratch, so
fed absolute colour it leaves an error floor of about the same size on every frame,
which on the dark game levels is most of the error (docs/comparison.md).

Channel widths are configurable. The paper gives them only in its Figure 4, which
our copy of the paper lacks; the defaults (feature extraction 32-32-8, reweighting
32-32-frames, U-Net 64-32 / 64-64 / 128-128 / 64-64 / 32-3) are our reading of it, and
``fast`` halves every U-Net width but the last (sec. 4.1). Depth is linear in [0,1]
(thesis sec. 4.5).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jtus import sampling
from jtus.data.conventions import FAR, NEAR, linearize_depth
from jtus.frame import Frame
from jtus.models import base, layers
from jtus.models.base import EXPOSURE, Cost, Model, Spec, bind

FEATURES = 12  # 8 learned + RGB-D
# conv_backward="auto" differentiates NSRR's 3x3 layers of at least WINOGRAD_CHANNELS
# (in, out) by Winograd on a CPU, on maps of at most WINOGRAD_PIXELS per device (batch x
# height x width): its training step at crop 128 (maps up to 2 x 128 x 128, the batch
# split over two devices) was faster with it; larger maps were not measured, and
# DLCTUS's trunk was slower by Winograd on 2 x 128 x 128 maps of 32 channels
WINOGRAD_PIXELS = 2 * 128 * 128
WINOGRAD_CHANNELS = (32, 16)


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    frames: int = 4
    extract: tuple = (32, 32, 8)
    reweight: tuple = (32, 32)
    unet: tuple = (64, 32, 64, 64, 128, 128, 64, 64, 32)
    fast: bool = False
    ycbcr: bool = False
    scale: float = 10.0
    near: float = NEAR
    far: float = FAR
    exposure: str = "absolute"  # or "normalized" (module docstring)
    # how the convolutions are differentiated: "custom" (layers.conv_same_fast),
    # "winograd" (layers.conv_same_winograd), "autodiff"; "auto": Config.conv_form
    conv_backward: str = "auto"

    def __post_init__(self):
        if self.extract[-1] != FEATURES - 4:
            raise ValueError(f"extract: the last width must be {FEATURES - 4}, got {self.extract}")
        if len(self.unet) != 9:
            raise ValueError(f"unet: expected 9 widths (the 10th layer outputs 3), got {self.unet}")
        if self.frames < 1:
            raise ValueError(f"frames: expected >= 1, got {self.frames}")
        if self.exposure not in EXPOSURE:
            raise ValueError(f"exposure: expected one of {EXPOSURE}, got {self.exposure!r}")
        if self.conv_backward not in layers.CONV_BACKWARDS:
            raise ValueError(f"conv_backward: expected one of {layers.CONV_BACKWARDS}, "
                             f"got {self.conv_backward!r}")

    def conv_form(self, backend=None, pixels=None, channels=None):
        """How a 3x3 convolution from ``channels = (in, out)`` over maps of ``pixels``
        (batch x height x width on one device) is differentiated on ``backend`` (JAX's
        default if None; None for the others: any). ``"winograd"`` (Winograd's F(4x4,
        3x3) forward and input gradient, ``layers.conv_same_winograd``) applies to the
        layers of at least ``WINOGRAD_CHANNELS`` and leaves narrower ones, where the
        transforms cost more than the multiplies they save (0.64-0.92x, layer by
        layer), to ``"custom"``. ``"auto"`` is ``"winograd"`` on a CPU for
        the full-width model on maps of at most ``WINOGRAD_PIXELS``, where its training
        step measured 1.03x as fast (docs/performance.md), and ``"custom"`` elsewhere:
        ``fast``'s halved widths (0.97x), larger maps and GPUs (not measured). Other
        kernel sizes take ``"custom"``'s backward under any form but ``"autodiff"``;
        without differentiation every form is ``layers.conv``."""
        form = self.conv_backward
        if form == "auto":
            cpu = (backend or jax.default_backend()) == "cpu"
            fits = pixels is None or pixels <= WINOGRAD_PIXELS
            form = "winograd" if cpu and fits and not self.fast else "custom"
        wide = channels is None or all(c >= m for c, m in zip(channels, WINOGRAD_CHANNELS))
        return "custom" if form == "winograd" and not wide else form

    def train_conv_form(self, batch, crop, backend=None):
        """The form of the widest layers of a training step on ``batch`` crops of
        ``crop`` HR pixels per device (``python -m jtus.bench`` records it)."""
        return self.conv_form(backend, batch * crop * crop)

    def unet_widths(self):
        return tuple(max(1, w // 2) for w in self.unet) if self.fast else self.unet


class State(NamedTuple):
    previous: jax.Array  # [B,H,W,frames*12] zero-up-sampled features in the last frame's view


def _conv_init(key, k, ci, co):
    return layers.torch_uniform_init(key, (k, k, ci, co))


def _stack(key, widths, ci):
    keys = jax.random.split(key, len(widths))
    out = []
    for k, co in zip(keys, widths):
        out.append(_conv_init(k, 3, ci, co))
        ci = co
    return out


def init(key, config: Config = Config()):
    k = jax.random.split(key, 4)
    n = config.frames
    u = config.unet_widths()
    cin = FEATURES * (1 + n)
    unet_in = [cin, u[0], u[1], u[2], u[3], u[4], u[5] + u[3], u[6], u[7] + u[1], u[8]]
    unet_out = list(u) + [3]
    ku = jax.random.split(k[3], 10)
    return {"extract_current": _stack(k[0], config.extract, 4),
            "extract_previous": _stack(k[1], config.extract, 4),
            "reweight": _stack(k[2], tuple(config.reweight) + (n,), 4 + 4 * n),
            "unet": [_conv_init(kk, 3, i, o) for kk, i, o in zip(ku, unet_in, unet_out)]}


def _conv(x, p, config):
    """``layers.conv_same`` differentiated as ``config.conv_form`` picks for its shape."""
    form = config.conv_form(pixels=math.prod(x.shape[:3]),
                            channels=p["kernel"].shape[2:])
    return layers.conv_same(x, p, form=form)


def _run(stack, x, config, last_relu=True):
    for i, p in enumerate(stack):
        x = _conv(x, p, config)
        if last_relu or i < len(stack) - 1:
            x = jax.nn.relu(x)
    return x


def _pool(x):
    b, h, w, c = x.shape
    return x.reshape(b, h // 2, 2, w // 2, 2, c).max((2, 4))


def _unet(ps, x, config):
    def conv2(x, i, last_relu=True):  # layers i and i + 1
        return _run(ps[i:i + 2], x, config, last_relu)

    s1 = conv2(x, 0)
    s2 = conv2(_pool(s1), 2)
    s3 = conv2(_pool(s2), 4)
    u2 = conv2(jnp.concatenate([sampling.upsample(s3, 2), s2], -1), 6)
    return conv2(jnp.concatenate([sampling.upsample(u2, 2), s1], -1), 8, last_relu=False)


def _rgbd(frame, config):
    color = frame.color.astype(jnp.float32) * base.exposure_normalizer(frame.color,
                                                                        config.exposure)
    if config.ycbcr:
        color = sampling.rgb_to_ycbcr(color)
    depth = linearize_depth(frame.depth.astype(jnp.float32), config.near, config.far)
    return jnp.concatenate([color, depth], -1)


def init_state(frame: Frame, config: Config = Config()) -> State:
    b, h, w, _ = frame.color.shape
    f = config.factor
    return State(jnp.zeros((b, h * f, w * f, FEATURES * config.frames), jnp.float32))


def features(params, frame, config):
    """(current features, this frame's features as a future previous frame), HR."""
    f = config.factor
    rgbd = _rgbd(frame, config)
    jit = frame.jitter.astype(jnp.float32)
    cur = jnp.concatenate([rgbd, _run(params["extract_current"], rgbd, config)], -1)
    prev = jnp.concatenate([rgbd, _run(params["extract_previous"], rgbd, config)], -1)
    return sampling.zero_upsample(cur, jit, f), sampling.zero_upsample(prev, jit, f)


def reweight_maps(params, cur, warped, config):
    """The per-previous-frame weights ``[B,H,W,frames]`` in [0, scale]."""
    n = config.frames
    rgbd_prev = [warped[..., i * FEATURES:i * FEATURES + 4] for i in range(n)]
    x = jnp.concatenate([cur[..., :4]] + rgbd_prev, -1)
    t = jnp.tanh(_run(params["reweight"], x, config, last_relu=False))
    return config.scale * (t + 1) / 2


def step(params, state: State, frame: Frame, config: Config = Config()):
    f = config.factor
    previous = state.previous
    if frame.reset is not None:
        previous = jnp.where(frame.reset[:, None, None, None], 0.0, previous)
    # The named scopes label the HLO for profiles (``Spec.stages``, python -m jtus.profile).
    with jax.named_scope("feature_extraction"):
        cur, as_prev = features(params, frame, config)
    with jax.named_scope("reprojection"):
        xy = sampling.reproject_coords(frame.motion.astype(jnp.float32), f)
        warped, inside = sampling.sample(previous, xy, "bilinear", return_mask=True)
        warped = jnp.where(inside, warped, 0.0)
    n = config.frames
    with jax.named_scope("reweighting"):
        wts = reweight_maps(params, cur, warped, config)
        scaled = [warped[..., i * FEATURES:(i + 1) * FEATURES] * wts[..., i:i + 1]
                  for i in range(n)]
    with jax.named_scope("reconstruction"):
        out = _unet(params["unet"], jnp.concatenate([cur] + scaled, -1), config)
        if config.ycbcr:
            out = sampling.ycbcr_to_rgb(out)
        if config.exposure == "normalized":
            out = out / base.exposure_normalizer(frame.color, config.exposure)
    with jax.named_scope("reprojection"):  # the warped features travel on
        new_prev = jnp.concatenate([as_prev, warped[..., :FEATURES * (n - 1)]], -1)
    return out, State(new_prev)


def normalize_exposure(params, config: Config, mean: float):
    """Parameters for ``exposure="normalized"`` that compute, on frames whose mean LR
    colour is ``mean``, what ``params`` (an NSRR fed absolute colour, ``config``)
    computes: the weights of every first layer that reads colour (both extractors, the
    reweighting network, the U-Net's input) are multiplied by ``mean`` on the colour
    channels, and the U-Net's last layer divided by it."""
    base.check_exposure_switch(config, mean)
    if config.ycbcr:
        raise ValueError("config: ycbcr inputs are affine in the colour, so scaled weights "
                         "cannot keep the outputs; expected ycbcr=False")
    n = config.frames

    def scaled(conv, blocks, width):
        c = conv["kernel"].shape[2]
        if c != blocks * width:
            raise ValueError(f"params: a first layer reads {c} channels, expected "
                             f"{blocks * width} for {config}")
        return layers.scale_inputs(conv, [b * width + i for b in range(blocks)
                                          for i in range(3)], mean)

    last = params["unet"][-1]
    return {"extract_current": [scaled(params["extract_current"][0], 1, 4)]
            + list(params["extract_current"][1:]),
            "extract_previous": [scaled(params["extract_previous"][0], 1, 4)]
            + list(params["extract_previous"][1:]),
            "reweight": [scaled(params["reweight"][0], 1 + n, 4)] + list(params["reweight"][1:]),
            "unet": [scaled(params["unet"][0], 1 + n, FEATURES)] + list(params["unet"][1:-1])
            + [{"kernel": last["kernel"] / mean, "bias": last["bias"] / mean}]}


def make(config: Config = Config()) -> Model:
    return bind(config, step, init=init, init_state=init_state)


def _conv_flops(kernel_shape, px):
    kh, kw, ci, co = kernel_shape[-4:]
    return (kh * kw * ci * co * 2 + co) * px


def cost(config: Config, H, W) -> Cost:
    p = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), config))
    px, lr = H * W, H * W // config.factor ** 2
    ext = sum(_conv_flops(q["kernel"].shape, lr) for k in ("extract_current", "extract_previous")
              for q in p[k])
    rew = sum(_conv_flops(q["kernel"].shape, px) for q in p["reweight"])
    scales = [px, px, px // 4, px // 4, px // 16, px // 16, px // 4, px // 4, px, px]
    unet = sum(_conv_flops(q["kernel"].shape, n) for q, n in zip(p["unet"], scales))
    feats = FEATURES * config.frames
    warp = px * feats * 4 * 2
    compulsory = 4 * (lr * 6 + 2 * px * feats + px * 3)
    act = 4 * 2 * px * (sum(config.unet_widths()) + feats * 2)
    # normalized: the frame's mean, the scaled LR colour and the scaled output
    norm = lr * 6 + px * 3 if config.exposure == "normalized" else 0
    return Cost(ext + rew + unet + warp + px * feats + norm, ext + rew + unet, compulsory,
                compulsory + act)


STAGES = ("feature_extraction", "reprojection", "reweighting", "reconstruction")

SPECS = (Spec("nsrr", make, lambda f: Config(factor=f), cost, trainable=True,
              torch_reference="torch_nsrr", stages=STAGES),
         Spec("nsrr-fast", make, lambda f: Config(factor=f, fast=True), cost, trainable=True,
              stages=STAGES))
