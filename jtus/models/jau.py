"""Jitter-aligned up-sampling (JAU, thesis sec. 4.1.1) as a stateless model."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from jtus import sampling
from jtus.frame import Frame
from jtus.models.base import Cost, Model, Spec, bind


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    method: str = "bilinear"  # or "bicubic" (Keys a=-0.75), any jtus.sampling method

    def __post_init__(self):
        if self.factor < 1:
            raise ValueError(f"factor: expected >= 1, got {self.factor}")
        if self.method not in sampling.METHODS:
            raise ValueError(f"method: expected one of {sampling.METHODS}, got {self.method!r}")


def step(params, state, frame: Frame, config: Config = Config()):
    out = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                           frame.jitter.astype(jnp.float32), config.factor,
                                           config.method)
    return out, state


def make(config: Config = Config()) -> Model:
    return bind(config, step)


def cost(config: Config, H, W) -> Cost:
    px = H * W
    taps = sampling.TAPS[config.method]
    lr = px // (config.factor ** 2)
    return Cost(px * 3 * taps * 2 + px * 10, 0.0, 4 * (lr * 3 + px * 3), 4 * (lr * 3 + px * 3))


SPECS = (Spec("jau", make, lambda f: Config(factor=f), cost),
         Spec("jau-bicubic", make, lambda f: Config(factor=f, method="bicubic"), cost))
