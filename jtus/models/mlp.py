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


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    hidden: tuple = (50, 50)
    gamma: float = 1.0        # residual boost: sign(r) |r|^(1/gamma)
    slope: float = 0.01       # leaky ReLU
    jitter: str = "dejitter"  # ignore | input | dejitter (module docstring)
    near: float = NEAR
    far: float = FAR

    def __post_init__(self):
        if self.jitter not in JITTER:
            raise ValueError(f"jitter: expected one of {JITTER}, got {self.jitter!r}")


def init(key, config: Config = Config()):
    sizes = (_inputs(config),) + tuple(config.hidden) + (config.factor ** 2,)
    return {"layers": layers.mlp_init(key, sizes)}


def _inputs(config):
    return 2 * P * P + (2 if config.jitter == "input" else 0)


def _boost(r, gamma):
    return r if gamma == 1.0 else jnp.sign(r) * jnp.abs(r) ** (1.0 / gamma)


def step(params, state, frame: Frame, config: Config = Config()):
    color = frame.color.astype(jnp.float32)
    depth = linearize_depth(frame.depth.astype(jnp.float32), config.near, config.far)
    if config.jitter == "dejitter":  # resampled to the pixel centres
        jit = frame.jitter.astype(jnp.float32)
        color = sampling.jitter_aligned_upsample(color, jit, 1)
        depth = sampling.jitter_aligned_upsample(depth, jit, 1)
    cp = sampling.neighbourhood(color, P)                # [B,h,w,3,25], edges replicated
    dp = sampling.neighbourhood(depth, P)                # [B,h,w,1,25]
    cmean = cp.mean(-1, keepdims=True)
    x = jnp.concatenate([_boost(cp - cmean, config.gamma),
                         jnp.broadcast_to(_boost(dp - dp.mean(-1, keepdims=True), config.gamma),
                                          cp.shape)], -1)  # [B,h,w,3,50]
    if config.jitter == "input":
        j = frame.jitter.astype(jnp.float32) - 0.5                # [B,2], from the centre
        x = jnp.concatenate([x, jnp.broadcast_to(j[:, None, None, None, :],
                                                 x.shape[:-1] + (2,))], -1)  # [B,h,w,3,52]
    for i, lyr in enumerate(params["layers"]):
        x = x @ lyr["kernel"] + lyr["bias"]
        if i < len(params["layers"]) - 1:
            x = jax.nn.leaky_relu(x, config.slope)
    out = x + cmean                                      # [B,h,w,3,f*f]
    b, h, w = color.shape[:3]
    out = out.reshape(b, h, w, 3 * config.factor ** 2)  # channel c*f*f + sub-pixel
    return sampling.pixel_shuffle(out, config.factor), state


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
    return Cost(dense + lr * 3 * 60 + dejitter, dense, compulsory,
                compulsory + 4 * 2 * lr * 3 * sum(sizes))


SPECS = (Spec("mlp", make, lambda f: Config(factor=f), cost, trainable=True, accept=acceptance),)
