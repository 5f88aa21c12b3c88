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

The state is ``[B,H,W,8]``: the output RGB and the hidden channels.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jtus import sampling
from jtus.data.conventions import linearize_depth
from jtus.frame import Frame
from jtus.models import layers
from jtus.models.base import Model, reset_select

HIDDEN = 5
K = 5  # kernel size
IN_CHANNELS = 3 + 1 + 2 + 3 + HIDDEN
SWITCHED = ("conv2", "conv3", "kernel")


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    width: int = 12
    jitter: str = "thesis"   # the sequence whose index selects the weight set
    near: float = 0.1
    far: float = 100.0

    def phases(self):
        return sampling.jitter_sequence(self.jitter, self.factor)


class State(NamedTuple):
    history: jax.Array  # [B,H,W,3+HIDDEN]


def init(key, config: Config = Config()):
    n = len(config.phases())
    w = config.width
    ks = jax.random.split(key, 5)

    def switched(k, size, ci, co):
        sets = [layers.torch_uniform_init(kk, (size, size, ci, co)) for kk in jax.random.split(k, n)]
        return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *sets)

    return {"conv1": layers.torch_uniform_init(ks[0], (3, 3, IN_CHANNELS, w)),
            "conv2": switched(ks[1], 3, w, w),
            "conv3": switched(ks[2], 5, w, w),
            "hidden": layers.torch_uniform_init(ks[3], (1, 1, w, HIDDEN)),
            "kernel": switched(ks[4], 5, w, 2 * K * K)}


def phase_index(jitter, config: Config):
    """The index of each frame's jitter in the sequence ``[B]`` (nearest entry)."""
    seq = jnp.asarray(config.phases(), jnp.float32)
    d = jnp.abs(jitter.astype(jnp.float32)[:, None, :] - seq[None]).sum(-1)
    return jnp.argmin(d, -1)


def _switched_conv(x, p, phase):
    """Per sample, the convolution with weight set ``phase[b]``."""
    def one(xb, k, b):
        return layers.conv(xb[None], k, b)[0]
    return jax.vmap(one)(x, p["kernel"][phase], p["bias"][phase])


def prepare(state: State, frame: Frame, config: Config):
    f = config.factor
    b, h, w, _ = frame.color.shape
    jit = frame.jitter.astype(jnp.float32)
    jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32), jit, f)
    mv = f * sampling.upsample(frame.motion.astype(jnp.float32), f)
    depth = sampling.upsample(linearize_depth(frame.depth.astype(jnp.float32), config.near,
                                              config.far), f)
    xy = sampling.pixel_grid(b, h * f, w * f) + mv
    rep, inside = sampling.sample(state.history, xy, "catmull_rom", return_mask=True)
    rep = jnp.where(inside, rep, 0.0)
    # a reset frame's history is the fresh input, unwarped (base.reset_select)
    fresh = jnp.concatenate([jau, jnp.zeros(jau.shape[:-1] + (HIDDEN,), jnp.float32)], -1)
    rep = reset_select(frame.reset, fresh, rep)
    return jnp.concatenate([jau, depth, mv, rep], -1), jau, rep


def kernels(params, x, phase):
    """``(weights [B,H,W,2*K*K] summing to one, hidden [B,H,W,5])``."""
    relu = jax.nn.relu
    h = relu(layers.conv_same(x, params["conv1"]))
    h = relu(_switched_conv(h, params["conv2"], phase))
    h = relu(_switched_conv(h, params["conv3"], phase))
    hidden = layers.conv_same(h, params["hidden"])
    logits = _switched_conv(h, params["kernel"], phase)
    return jax.nn.softmax(logits, -1), hidden


def step(params, state: State, frame: Frame, config: Config = Config()):
    x, jau, rep = prepare(state, frame, config)
    wts, hidden = kernels(params, x, phase_index(frame.jitter, config))
    n = K * K
    def near(img):  # zero-padded KxK neighbourhoods, raster order
        return sampling.neighbourhood(img, K, mode="constant")

    out = (jnp.einsum("bhwcn,bhwn->bhwc", near(jau), wts[..., :n])
           + jnp.einsum("bhwcn,bhwn->bhwc", near(rep[..., :3]), wts[..., n:]))
    return out, State(jnp.concatenate([out, hidden], -1))


def init_state(frame: Frame, config: Config = Config()) -> State:
    jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                           frame.jitter.astype(jnp.float32), config.factor)
    return State(jnp.concatenate([jau, jnp.zeros(jau.shape[:-1] + (HIDDEN,), jnp.float32)], -1))


def make(config: Config = Config()) -> Model:
    return Model(init=lambda key: init(key, config),
                 init_state=lambda frame: init_state(frame, config),
                 step=lambda params, state, frame: step(params, state, frame, config),
                 config=config)


def alias_mask(jau, target, sensitivity=4.0):
    """Herveau et al.'s per-pixel aliasing mask: the summed channel differences between
    the (jitter-aligned) input and the reference, scaled, clipped to [0, 1], 3x3-dilated."""
    m = jnp.clip(sensitivity * jnp.abs(jau - target).sum(-1, keepdims=True), 0.0, 1.0)
    return sampling.neighbourhood(m, 3).max(-1)


def make_loss(factor, weights=(1.0, 1.0, 10.0), alias_boost=1.5, sensitivity=4.0):
    """The paper's training loss (sec. 5.3): reference (L1), gradient (L1 of x and y
    differences) and temporal (the current error against the warped previous error)
    terms, each split by the alias mask M into ``alias_boost * M`` and ``1 - M`` parts."""
    from jtus import losses

    wr, wg, wt = weights

    def grad(x):
        return x[:, 1:, :-1] - x[:, :-1, :-1], x[:, :-1, 1:] - x[:, :-1, :-1]

    def loss(out, target, prev_out, prev_target, has_prev, frame):
        jau = sampling.jitter_aligned_upsample(frame.color.astype(jnp.float32),
                                               frame.jitter.astype(jnp.float32), factor)
        m = alias_mask(jau, target, sensitivity)
        wgt = alias_boost * m + (1 - m)
        ref = jnp.mean(wgt * jnp.abs(out - target))
        gy_o, gx_o = grad(out)
        gy_t, gx_t = grad(target)
        wc = wgt[:, :-1, :-1]
        g = jnp.mean(wc * (jnp.abs(gy_o - gy_t) + jnp.abs(gx_o - gx_t)))
        x, y = losses.errors(out, target, prev_out, prev_target, has_prev, frame, factor)
        t = jnp.mean(wgt * jnp.abs(x - y))
        return wr * ref + wg * g + wt * t

    return loss


__all__ = ["Config", "State", "alias_mask", "init", "init_state", "kernels", "make",
           "make_loss", "phase_index", "prepare", "step"]
