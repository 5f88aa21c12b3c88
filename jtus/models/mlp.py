"""The MLP upscaler (Spencer, *Deep Upscaling*): a per-input-pixel multilayer
perceptron on 5x5 patches.

For each LR pixel and each colour channel (weights shared across channels): the 5x5
patch of that channel and the 5x5 patch of linear depth, each with its mean removed
(the DC term, which otherwise makes the network a bilinear filter), optionally
boosted by a signed gamma ramp; two hidden layers of 50 with leaky ReLU; an output of
f x f sub-pixels, to which the colour patch's mean is added back; pixel shuffle to HR.
Stateless (the original is single-frame). Borders replicate the edge.

Adaptation to jittered input (``jitter``): the original upscales frames rendered at
pixel centres; here every frame is rendered with a sub-pixel jitter that the colours do
not reveal, and an upscaler that ignores it places every sample up to half an LR pixel
off. Three choices, measured on the ``diverse`` validation seeds at 4x
(docs/comparison.md): ``"ignore"`` (the original's input), ``"input"`` (the jitter's
offset from the pixel centre, ``jitter - 0.5``, appended to every patch as two more
values) and ``"dejitter"`` (the default: colour and depth are first resampled to the
pixel centres by jitter-aligned bilinear interpolation at factor 1, thesis sec. 4.1.1,
so the network sees the frame the original was built for).

What the sub-pixels are relative to (``base``): ``"mean"`` (the original) adds the colour
patch's mean back, so the network must rebuild the interpolation from the mean-removed
patch; ``"jau"`` adds jitter-aligned bilinear up-sampling of the current frame instead
(thesis sec. 4.1.1), so the network predicts only its correction: its output layer
starts at zero, so the untrained model is JAU exactly (docs/comparison.md).

Contrast normalization (``contrast``): the mean-removed colour and depth patches are
divided by their mean absolute deviation (plus ``EPS``) and the network's output is
multiplied by the colour patch's, so a flat patch gets no change at any brightness and
a correction scales with the contrast it corrects (the dark game levels' errors stay
as small as their signal).

Training patches are accepted with a probability rising with their gradient
magnitude (``acceptance``), as in the original's data pipeline.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jtus import sampling
from jtus.data.conventions import FAR, NEAR, linearize_depth
from jtus.frame import Frame
from jtus.models import layers
from jtus.models.base import Cost, Model, Spec, bind

P = 5
JITTER = ("ignore", "input", "dejitter")
BASES = ("mean", "jau")
EPS = 1e-4  # added to a patch's deviation before dividing by it (``contrast``)


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    hidden: tuple = (50, 50)
    gamma: float = 1.0        # residual boost: sign(r) |r|^(1/gamma)
    slope: float = 0.01       # leaky ReLU
    jitter: str = "dejitter"  # ignore | input | dejitter (module docstring)
    base: str = "mean"        # mean | jau: what the network's output is added to
    contrast: bool = False    # patches at unit deviation, the output at the patch's
    near: float = NEAR
    far: float = FAR

    def __post_init__(self):
        if self.jitter not in JITTER:
            raise ValueError(f"jitter: expected one of {JITTER}, got {self.jitter!r}")
        if self.base not in BASES:
            raise ValueError(f"base: expected one of {BASES}, got {self.base!r}")


def init(key, config: Config = Config()):
    sizes = (_inputs(config),) + tuple(config.hidden) + (config.factor ** 2,)
    dense = layers.mlp_init(key, sizes)
    if config.base == "jau":  # a zero correction: the untrained model is JAU
        dense[-1] = jax.tree.map(jnp.zeros_like, dense[-1])
    return {"layers": dense}


def _inputs(config):
    return 2 * P * P + (2 if config.jitter == "input" else 0)


def _boost(r, gamma):
    return r if gamma == 1.0 else jnp.sign(r) * jnp.abs(r) ** (1.0 / gamma)


def _deviation(r):
    return jnp.abs(r).mean(-1, keepdims=True)


def patches(frame: Frame, config: Config):
    """The network's input ``[B,h,w,3,n]`` per LR pixel and colour channel, the colour
    patches' means ``[B,h,w,3,1]`` and, with ``contrast``, the colour patches' mean
    absolute deviation, which the output is multiplied by (ones without)."""
    color = frame.color.astype(jnp.float32)
    jit = frame.jitter.astype(jnp.float32)
    depth = linearize_depth(frame.depth.astype(jnp.float32), config.near, config.far)
    if config.jitter == "dejitter":  # resampled to the pixel centres
        color = sampling.jitter_aligned_upsample(color, jit, 1)
        depth = sampling.jitter_aligned_upsample(depth, jit, 1)
    cp = sampling.neighbourhood(color, P)                # [B,h,w,3,25], edges replicated
    dp = sampling.neighbourhood(depth, P)                # [B,h,w,1,25]
    cmean = cp.mean(-1, keepdims=True)
    c, d = cp - cmean, dp - dp.mean(-1, keepdims=True)
    scale = jnp.ones_like(cmean)
    if config.contrast:  # unit deviation in, the patch's deviation out
        scale = _deviation(c)
        c, d = c / (scale + EPS), d / (_deviation(d) + EPS)
    x = jnp.concatenate([_boost(c, config.gamma),
                         jnp.broadcast_to(_boost(d, config.gamma), cp.shape)], -1)
    if config.jitter == "input":
        j = jit - 0.5                                              # [B,2], from the centre
        x = jnp.concatenate([x, jnp.broadcast_to(j[:, None, None, None, :],
                                                 x.shape[:-1] + (2,))], -1)  # [B,h,w,3,52]
    return x, cmean, scale


def step(params, state, frame: Frame, config: Config = Config()):
    # The named scopes label the HLO for profiles (``Spec.stages``, python -m jtus.profile).
    with jax.named_scope("patches"):
        x, cmean, scale = patches(frame, config)
    with jax.named_scope("network"):
        for i, lyr in enumerate(params["layers"]):
            x = x @ lyr["kernel"] + lyr["bias"]
            if i < len(params["layers"]) - 1:
                x = jax.nn.leaky_relu(x, config.slope)
    with jax.named_scope("output"):
        if config.contrast:
            x = x * scale
        out = x + cmean if config.base == "mean" else x     # [B,h,w,3,f*f]
        b, h, w = frame.color.shape[:3]
        out = out.reshape(b, h, w, 3 * config.factor ** 2)  # channel c*f*f + sub-pixel
        out = sampling.pixel_shuffle(out, config.factor)
        if config.base == "jau":
            out = out + sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                                         frame.jitter.astype(jnp.float32),
                                                         config.factor)
    return out, state


def acceptance(target, scale=0.05):
    """Probability of keeping a training crop ``[T,H,W,3]``: rises with its mean
    gradient magnitude, ``min(1, g / scale)``, with a floor so flat crops still occur."""

    t = np.asarray(target, np.float32).mean(-1)
    g = np.abs(np.diff(t, axis=-1)).mean() + np.abs(np.diff(t, axis=-2)).mean()
    return float(min(1.0, max(0.05, g / scale)))


def make(config: Config = Config()) -> Model:
    return bind(config, step, init=init)


def cost(config: Config, H, W) -> Cost:
    lr = H * W // config.factor ** 2
    sizes = (_inputs(config),) + tuple(config.hidden) + (config.factor ** 2,)
    dense = sum(i * o * 2 + o for i, o in zip(sizes[:-1], sizes[1:])) * lr * 3
    compulsory = 4 * (lr * 4 + H * W * 3)
    # de-jittering: a 4-tap bilinear read (4 multiply-adds) per LR pixel and channel
    dejitter = lr * 4 * 8 if config.jitter == "dejitter" else 0
    # the JAU base: a 4-tap bilinear read per HR pixel and channel, plus the add
    base = H * W * 3 * (4 * 2 + 1) if config.base == "jau" else 0
    return Cost(dense + lr * 3 * 60 + dejitter + base, dense, compulsory,
                compulsory + 4 * 2 * lr * 3 * sum(sizes))


STAGES = ("patches", "network", "output")

SPECS = (Spec("mlp", make, lambda f: Config(factor=f), cost, trainable=True, accept=acceptance,
              stages=STAGES),)
