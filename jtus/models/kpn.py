"""Minimal kernel-prediction TAA (Herveau et al.), adapted to up-sampling.

Input at HR: the jitter-aligned current colour (bilinear JAU), linear depth and motion
(up-sampled bilinearly, in HR pixels), and the reprojected history: the previous
output RGB and 5 hidden channels, read with Catmull-Rom at ``P + f * mv`` (zero where
that leaves the frame). Network (the paper's Table 2): 3x3 conv to 12, 3x3 conv to 12,
5x5 conv to 12 (ReLU after each), then a 1x1 conv to the 5 hidden channels and a 5x5
conv to 50 weights: two 5x5 kernels, normalized together by a softmax so that they sum
to one, applied to the 5x5 neighbourhoods of the current JAU colour and of the
reprojected history RGB (eq. 3). The last three layers (the second and third
convolutions and the kernel layer) switch between per-jitter-phase weight sets: phase
``k`` is the index of the frame's jitter in the sequence, so the operation count does
not grow with the number of phases.

Adaptation to up-sampling (``sample_mask``): the JAU colour is smooth and a
convolution is translation-invariant, so nothing in the paper's input tells the network
which HR pixels hold this frame's samples, which is what jitter-aware accumulation (TUS's
box β) needs. With ``sample_mask`` one more input channel is 1 on the HR pixel under
each jittered sample and 0 elsewhere (``sampling.zero_upsample`` of ones).

``current="samples"`` goes further: the current kernel mixes this frame's samples
themselves, each at the HR pixel under it (``sampling.zero_upsample``), instead of the
smooth JAU colour. The mask and the placed samples are inputs too, and the softmax
runs over the taps that hold a sample plus the 25 history taps, so a pixel's output
is a normalized mix of the samples near it and of its history: the jitter-aware
accumulation of TUS, with weights the network predicts. The kernel layer's bias then
starts there (``SAMPLES_PRIOR``): the history's centre tap ``log 9`` above a sample
on the pixel itself, every other tap 5 below it, so that an untrained network
accumulates each pixel's samples with weight about 0.1 and keeps its history
elsewhere. At 2x and 4x every 5x5 window off the border holds at least one sample;
the 25 history taps keep the softmax defined where a border window holds none.

``history="clamped"`` clamps the reprojected history's RGB, per channel, to the min
and max of the 3x3 LR samples around each HR pixel's nearest sample
(``sampling.neighbourhood_box``, TUS's ``clamp``) before it enters the network and the
history kernel. A softmax mix of the history cannot leave the range of its taps, so a
history the scene has left behind (a light that dims while the camera holds still)
would otherwise stay in the output for as long as the network keeps weighting it.

``exposure="normalized"`` divides the colour the network sees (the JAU colour, the
history's RGB and the placed samples) by the frame's mean LR colour (each batch
element's own, over pixels and channels, floored at ``EXPOSURE_FLOOR``); the kernels
still mix the colours as they are. The network's weights then do not depend on the
scene's exposure: scaling a video's colour by ``s`` scales every output by ``s``, as it
does TUS's, where a network fed absolute colour can learn one blend for dark levels
and another for bright ones (docs/comparison.md: tried, and not adopted).

The state is ``[B,H,W,8]``: the output RGB and the hidden channels.
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
from jtus.models.base import Cost, Model, Spec, bind, reset_select

HIDDEN = 5
K = 5  # kernel size
# prepare's input: JAU colour (0-2), depth (3), motion (4-5), history RGB (6-8) and
# hidden channels (9-13); then the sample mask (channel IN_CHANNELS) and, for the
# samples mix, the placed samples (the last three)
IN_CHANNELS = 3 + 1 + 2 + 3 + HIDDEN
COLOUR_INPUTS = (0, 1, 2, 6, 7, 8)  # the colour channels among the first IN_CHANNELS
SWITCHED = ("conv2", "conv3", "kernel")
CURRENT = ("jau", "samples")
HISTORY = ("raw", "clamped")
EXPOSURE = base.EXPOSURE
EXPOSURE_FLOOR = base.EXPOSURE_FLOOR
# current="samples": the kernel layer's starting bias (logits) for the history's centre
# tap, a sample on the pixel itself, and every other tap (module docstring)
SAMPLES_PRIOR = {"history_centre": math.log(9.0), "sample_centre": 0.0, "other": -5.0}


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    width: int = 12
    jitter: str = "thesis"   # the sequence whose index selects the weight set
    sample_mask: bool = False  # one more input: 1 where this frame's sample lands
    current: str = "jau"     # what the current kernel mixes: "jau" or "samples"
    history: str = "raw"     # "clamped": the history RGB clamped to the samples' 3x3 box
    exposure: str = "absolute"  # "normalized": network colour over the frame's mean colour
    near: float = NEAR
    far: float = FAR

    def __post_init__(self):
        if self.current not in CURRENT:
            raise ValueError(f"current: expected one of {CURRENT}, got {self.current!r}")
        if self.history not in HISTORY:
            raise ValueError(f"history: expected one of {HISTORY}, got {self.history!r}")
        if self.exposure not in EXPOSURE:
            raise ValueError(f"exposure: expected one of {EXPOSURE}, got {self.exposure!r}")

    def marks_samples(self):
        """Whether the input holds the sample mask (``sample_mask`` or the samples mix)."""
        return self.sample_mask or self.current == "samples"

    def in_channels(self):
        return IN_CHANNELS + int(self.marks_samples()) + 3 * int(self.current == "samples")

    def phases(self):
        return sampling.jitter_sequence(self.jitter, self.factor)


class State(NamedTuple):
    history: jax.Array  # [B,H,W,3+HIDDEN]


def init(key, config: Config = Config()):
    n = len(config.phases())
    w = config.width
    ks = jax.random.split(key, 5)

    def switched(k, size, ci, co):
        sets = [layers.torch_uniform_init(kk, (size, size, ci, co))
                for kk in jax.random.split(k, n)]
        return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *sets)

    return {"conv1": layers.torch_uniform_init(ks[0], (3, 3, config.in_channels(), w)),
            "conv2": switched(ks[1], 3, w, w),
            "conv3": switched(ks[2], 5, w, w),
            "hidden": layers.torch_uniform_init(ks[3], (1, 1, w, HIDDEN)),
            "kernel": _kernel_bias(switched(ks[4], 5, w, 2 * K * K), config)}


def _kernel_bias(kernel, config: Config):
    """The kernel layer, its bias set to ``SAMPLES_PRIOR`` for the samples mix."""
    if config.current != "samples":
        return kernel
    centre = K * K // 2
    bias = jnp.full((2 * K * K,), SAMPLES_PRIOR["other"], jnp.float32)
    bias = bias.at[centre].set(SAMPLES_PRIOR["sample_centre"])
    bias = bias.at[K * K + centre].set(SAMPLES_PRIOR["history_centre"])
    return {**kernel, "bias": jnp.broadcast_to(bias, kernel["bias"].shape)}


def adapt_params(params, config: Config = Config(sample_mask=True)):
    """Parameters of a KPN without the sample mask grown to ``config``'s inputs: the
    first convolution gains a zero weight for the mask channel (channel
    ``IN_CHANNELS``, after the others of the JAU mix), so the grown network computes
    what the given one does until training moves it. Parameters that already fit are
    returned as they are; ``python -m jtus.train --init-from`` calls this."""
    conv1 = params["conv1"]
    kernel = conv1["kernel"]
    have, want = kernel.shape[2], config.in_channels()
    if have == want:
        return params
    if (have, want) != (IN_CHANNELS, IN_CHANNELS + 1) or config.current != "jau":
        raise ValueError(f"params: conv1 takes {have} input channels, this config takes "
                         f"{want}; only the sample-mask channel is added to a KPN of the "
                         f"JAU mix")
    zero = jnp.zeros(kernel.shape[:2] + (1,) + kernel.shape[3:], kernel.dtype)
    return {**params, "conv1": {**conv1, "kernel": jnp.concatenate([kernel, zero], 2)}}


def normalize_exposure(params, config: Config, mean: float):
    """Parameters for ``exposure="normalized"`` that compute, on a frame whose mean LR
    colour is ``mean``, what ``params`` (a KPN fed absolute colour, ``config``) computes:
    the first convolution's weights for the colour inputs (the JAU colour, the history
    RGB and, for the samples mix, the placed samples) are multiplied by ``mean``, so
    that training starts from what the network already does at that exposure."""
    base.check_exposure_switch(config, mean)
    conv1 = params["conv1"]
    n = conv1["kernel"].shape[2]
    if n != config.in_channels():
        raise ValueError(f"params: conv1 takes {n} input channels, expected "
                         f"{config.in_channels()} for {config}")
    colour = list(COLOUR_INPUTS) + ([n - 3, n - 2, n - 1] if config.current == "samples"
                                    else [])
    return {**params, "conv1": layers.scale_inputs(conv1, colour, mean)}


def phase_index(jitter, config: Config):
    """The index of each frame's jitter in the sequence ``[B]`` (nearest entry)."""
    seq = jnp.asarray(config.phases(), jnp.float32)
    d = jnp.abs(jitter.astype(jnp.float32)[:, None, :] - seq[None]).sum(-1)
    return jnp.argmin(d, -1)


def _switched_conv(x, p, phase):
    """Per sample, the convolution with weight set ``phase[b]``: one convolution per
    batch element (a static loop). A ``vmap`` over per-sample kernels becomes a
    grouped convolution whose backward XLA:CPU runs about 10x slower than this in a
    training scan (docs/results/cpu-speed/result.md, "Training speed")."""
    return jnp.concatenate([layers.conv_same(x[i:i + 1], {"kernel": p["kernel"][phase[i]],
                                                          "bias": p["bias"][phase[i]]})
                            for i in range(x.shape[0])], 0)


def prepare(state: State, frame: Frame, config: Config):
    f = config.factor
    jit = frame.jitter.astype(jnp.float32)
    # The named scopes label the HLO for profiles (``Spec.stages``, python -m jtus.profile).
    with jax.named_scope("input_upsampling"):
        jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32), jit, f)
        mv = f * sampling.upsample(frame.motion.astype(jnp.float32), f)
        depth = sampling.upsample(linearize_depth(frame.depth.astype(jnp.float32),
                                                  config.near, config.far), f)
        cur = jau
        if config.current == "samples":
            cur = sampling.zero_upsample(frame.color.astype(jnp.float32), jit, f)
    with jax.named_scope("reprojection"):
        xy = sampling.reproject_coords(frame.motion.astype(jnp.float32), f)
        rep, inside = sampling.sample(state.history, xy, "catmull_rom", return_mask=True)
        rep = jnp.where(inside, rep, 0.0)
        # a reset frame's history is the fresh input, unwarped (base.reset_select)
        fresh = jnp.concatenate([jau, jnp.zeros(jau.shape[:-1] + (HIDDEN,), jnp.float32)], -1)
        rep = reset_select(frame.reset, fresh, rep)
        if config.history == "clamped":
            rep = clamp_history(rep, frame, config)
    with jax.named_scope("network"):  # its input
        scale = exposure_scale(frame, config)
        parts = [jau * scale, depth, mv, rep[..., :3] * scale, rep[..., 3:]]
        if config.marks_samples():
            parts.append(sample_mask(frame, config))
        if config.current == "samples":
            parts.append(cur * scale)
        x = jnp.concatenate(parts, -1)
    return x, cur, rep


def exposure_scale(frame: Frame, config: Config):
    """What the network's colour inputs are multiplied by: ``1.0`` for
    ``exposure="absolute"`` (a Python float, so the graph is unchanged), else ``[B,1,1,1]``,
    one over each frame's mean LR colour (at least ``EXPOSURE_FLOOR``)."""
    return base.exposure_normalizer(frame.color, config.exposure)


def clamp_history(rep, frame: Frame, config: Config):
    """The reprojected state ``rep [B,H,W,8]`` with its RGB clamped, per channel, to
    the min and max of the 3x3 LR samples around each HR pixel's nearest sample
    (``sampling.neighbourhood_box``, TUS's ``clamp`` rectification); the hidden channels
    pass unchanged."""
    b, h, w, _ = frame.color.shape
    xy = sampling.jitter_aligned_coords(frame.jitter, b, h, w, config.factor)
    lo, hi = sampling.neighbourhood_box(frame.color.astype(jnp.float32), xy)
    return jnp.concatenate([jnp.clip(rep[..., :3], lo, hi), rep[..., 3:]], -1)


def sample_mask(frame: Frame, config: Config):
    """``[B,H,W,1]``: 1 on the HR pixel under each of this frame's samples, else 0."""
    return sampling.zero_upsample(jnp.ones(frame.depth.shape, jnp.float32),
                                  frame.jitter.astype(jnp.float32), config.factor)


def _near(img):
    """Zero-padded KxK neighbourhoods in raster order, ``[B,H,W,C,K*K]``."""
    return sampling.neighbourhood(img, K, mode="constant")


def kernels(params, x, phase, valid=None):
    """``(weights [B,H,W,2*K*K] summing to one, hidden [B,H,W,5])``; ``valid``
    (``[B,H,W,2*K*K]`` booleans, optional) leaves taps out of the softmax (weight 0)."""
    relu = jax.nn.relu
    h = relu(layers.conv_same(x, params["conv1"]))
    h = relu(_switched_conv(h, params["conv2"], phase))
    h = relu(_switched_conv(h, params["conv3"], phase))
    hidden = layers.conv_same(h, params["hidden"])
    logits = _switched_conv(h, params["kernel"], phase)
    return jax.nn.softmax(logits, -1, where=valid), hidden


def valid_taps(x, config: Config):
    """The taps the softmax runs over, ``[B,H,W,2*K*K]``: every tap for the JAU mix;
    for the samples mix, the current taps that hold a sample (read from the sample
    mask in ``prepare``'s input ``x``) and every history tap."""
    if config.current == "jau":
        return None
    cur = _near(x[..., IN_CHANNELS:IN_CHANNELS + 1])[..., 0, :] > 0.5
    return jnp.concatenate([cur, jnp.ones_like(cur)], -1)


def step(params, state: State, frame: Frame, config: Config = Config()):
    x, cur, rep = prepare(state, frame, config)
    with jax.named_scope("network"):
        wts, hidden = kernels(params, x, phase_index(frame.jitter, config),
                              valid_taps(x, config))
    n = K * K
    with jax.named_scope("output"):
        out = (sampling.filter_neighbourhood(cur, wts[..., :n], K, mode="constant")
               + sampling.filter_neighbourhood(rep[..., :3], wts[..., n:], K, mode="constant"))
        new = State(jnp.concatenate([out, hidden], -1))
    return out, new


def init_state(frame: Frame, config: Config = Config()) -> State:
    jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                           frame.jitter.astype(jnp.float32), config.factor)
    return State(jnp.concatenate([jau, jnp.zeros(jau.shape[:-1] + (HIDDEN,), jnp.float32)], -1))


def make(config: Config = Config()) -> Model:
    return bind(config, step, init=init, init_state=init_state)


def cost(config: Config, H, W) -> Cost:
    p = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), config))
    px, lr = H * W, H * W // config.factor ** 2

    def conv(shape, n):
        kh, kw, ci, co = shape[-4:]
        return (kh * kw * ci * co * 2 + co) * n

    net = sum(conv(p[k]["kernel"].shape, px) for k in ("conv1", "conv2", "conv3", "hidden",
                                                       "kernel"))
    n = 2 * K * K
    apply = px * (n * 3 * 2 + n * 4)  # the two kernels on 3 channels, softmax
    warp = px * (16 * 8 * 2 + 20) + px * 4 * 3 * 2
    if config.history == "clamped":  # min and max of 9 samples at LR, then a clip at HR
        warp += lr * 2 * 8 * 3 + px * 2 * 3
    if config.exposure == "normalized":  # the frame's mean, then the colour inputs scaled
        warp += lr * 3 + px * 3 * (2 + int(config.current == "samples"))
    compulsory = 4 * (lr * 6 + 2 * px * 8 + px * 3)
    act = 4 * 2 * px * (config.in_channels() + 3 * config.width + n + HIDDEN)
    return Cost(net + apply + warp, net, compulsory, compulsory + act)


# trained with the paper's alias-masked loss (jtus.losses.kpn_loss)
STAGES = ("input_upsampling", "reprojection", "network", "output")

SPECS = (Spec("kpn", make, lambda f: Config(factor=f), cost, trainable=True, loss="kpn",
              torch_reference="torch_kpn", adapt=adapt_params, stages=STAGES),)




__all__ = ["COLOUR_INPUTS", "CURRENT", "Config", "EXPOSURE", "EXPOSURE_FLOOR", "HISTORY",
           "SAMPLES_PRIOR", "SPECS", "STAGES", "State", "adapt_params", "clamp_history", "cost",
           "exposure_scale", "init", "init_state", "kernels", "make", "normalize_exposure",
           "phase_index", "prepare", "sample_mask", "step", "valid_taps"]
