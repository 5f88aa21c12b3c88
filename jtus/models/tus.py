"""Classical temporal up-sampling (TUS/TAA, thesis sec. 2.4, eq. 34-42).

Per frame, at HR:

1. the input scaled to HR (eq. 38): with the ``tent`` filter (eq. 40, one LR pixel
   wide) this is exactly bilinear jitter-aligned up-sampling; with ``gaussian``
   (eq. 41, ``sigma`` in HR pixels) the 3x3 LR samples around the HR pixel are
   weighted by their distance and normalized;
2. the history reprojected with any warp (motion optionally 3x3-dilated), padded with
   the scaled input where it leaves the previous frame (as DLCTUS, sec. 5.3.1);
3. history rectification against the box of the 3x3 LR samples around the HR pixel,
   in RGB or YCoCg: ``clamp`` (per channel) or ``clip`` (toward the samples' mean,
   onto the box), or ``none``;
4. accumulation ``f = αβ s + (1 - αβ) h`` (eq. 39) with α constant or 1/N (the count N
   travels in the history's fourth channel) and β ``box`` (1 on the HR pixel that holds
   this frame's sample, else 0: Yang et al.'s one-pixel box), ``max`` (the largest
   unnormalized filter weight, eq. 42) or ``one``.

The state is the history ``[B,H,W,4]``: RGB and the sample count N.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jtus import sampling
from jtus.frame import Frame
from jtus.models.base import Cost, Model, Spec, bind, reset_select

RECTIFY = ("clamp", "clip", "none")
FILTERS = ("tent", "gaussian")
BETAS = ("box", "max", "one")
COUNTS = ("frames", "samples")


@dataclasses.dataclass(frozen=True)
class Config:
    factor: int = 4
    hdr: bool = False        # trained on tone-mapped HDR colour (base.exposed_parts)
    warp: str = "bicubic"
    warp_a: float = -0.75
    rectify: str = "clamp"
    color_space: str = "rgb"        # rgb | ycocg: where the neighbourhood box is taken
    alpha: float = 1.0              # constant α, or the floor of 1/N with inverse_count
    inverse_count: bool = False     # α = max(1/N, alpha)
    filter: str = "tent"
    sigma: float = 0.47             # Gaussian filter width in HR pixels (UE4-like)
    beta: str = "box"
    dilation: bool = False
    count: str = "frames"           # what N counts: every frame, or the samples a pixel
                                    # received (N += β; with inverse_count a per-pixel
                                    # running mean of its samples, which converges)

    def __post_init__(self):
        checks = (("rectify", self.rectify, RECTIFY), ("filter", self.filter, FILTERS),
                  ("beta", self.beta, BETAS), ("color_space", self.color_space, ("rgb", "ycocg")),
                  ("warp", self.warp, sampling.METHODS), ("count", self.count, COUNTS))
        for name, value, allowed in checks:
            if value not in allowed:
                raise ValueError(f"{name}: expected one of {allowed}, got {value!r}")
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"alpha: expected a value in (0, 1], got {self.alpha}")
        if self.factor < 1:
            raise ValueError(f"factor: expected >= 1, got {self.factor}")


def thesis(factor) -> Config:
    """The thesis's TUS (sec. 5.3.1): clamping, bicubic reprojection, no dilation,
    α = 0.5 at 2x and 1.0 at 4x, tent filter with Yang et al.'s box β."""
    return Config(factor=factor, alpha=0.5 if factor == 2 else 1.0)


def running_mean(factor) -> Config:
    """Accumulation as a per-pixel running mean of the samples each HR pixel received
    (Yang et al.'s box β, α = 1/N counting samples, floor 0.001), without rectification:
    on a static hold it converges (tests/test_hard_cases.py); under motion it ghosts."""
    return Config(factor=factor, rectify="none", inverse_count=True, alpha=0.001,
                  count="samples")


PRESETS = {"tus": thesis, "tus-clip": lambda f: dataclasses.replace(thesis(f), rectify="clip",
                                                                      color_space="ycocg"),
           "tus-mean": running_mean}


class State(NamedTuple):
    history: jax.Array  # [B,H,W,4] RGB and sample count N


_OFFSETS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]


def _jau_coords(frame, f):
    b, h, w, _ = frame.color.shape
    return sampling.jitter_aligned_coords(frame.jitter, b, h, w, f)


def _scaled_input(config, color, xy):
    """(s [B,H,W,3], β_max [B,H,W,1]) per eq. 38 and 42."""
    f = config.factor
    if config.filter == "tent":
        s = sampling.sample(color, xy, "bilinear")
        u = xy - 0.5  # sample j sits at u = j
        d = u - jnp.round(u)  # to the nearest sample: |d| <= 1/2, so the tent is 1 - |d|
        beta = jnp.prod(1 - jnp.abs(d), -1, keepdims=True)
        return s, beta
    u = xy - 0.5
    n = jnp.floor(u + 0.5)
    num, den, beta = 0.0, 0.0, 0.0
    for dy, dx in _OFFSETS:
        off = jnp.asarray([dx, dy], jnp.float32)
        d = (n + off - u) * f  # distance to that sample in HR pixels
        wgt = jnp.exp(-(d * d).sum(-1, keepdims=True) / (2 * config.sigma ** 2))
        num = num + wgt * sampling.sample(color, n + off + 0.5, "nearest")
        den = den + wgt
        beta = jnp.maximum(beta, wgt)
    return num / den, beta


def _beta(config, frame, beta_max):
    if config.beta == "one":
        return jnp.ones_like(beta_max)
    if config.beta == "max":
        return beta_max
    b, h, w, _ = frame.color.shape
    ones = jnp.ones((b, h, w, 1), jnp.float32)
    return sampling.zero_upsample(ones, frame.jitter.astype(jnp.float32), config.factor)


def _rectify(config, hist, color, xy):
    if config.rectify == "none":
        return hist
    to = sampling.rgb_to_ycocg if config.color_space == "ycocg" else (lambda x: x)
    back = sampling.ycocg_to_rgb if config.color_space == "ycocg" else (lambda x: x)
    h = to(hist)
    if config.rectify == "clamp":
        lo, hi = sampling.neighbourhood_box(to(color), xy)
        return back(jnp.clip(h, lo, hi))
    # clip the segment mean -> h onto the box
    lo, hi, mean = sampling.neighbourhood_box(to(color), xy, True)
    v = h - mean
    # per channel, how far along v the box's face is (>= 0: lo <= mean <= hi); a channel
    # with v = 0 sets no bound (its unselected quotient may be inf or nan: never read)
    t = jnp.where(v > 0, (hi - mean) / v, jnp.where(v < 0, (lo - mean) / v, jnp.inf))
    t = jnp.minimum(jnp.min(t, -1, keepdims=True), 1.0)
    return back(mean + t * v)


def _fresh(s):
    """A reset history: the scaled input with N = 0. The step then counts the
    current frame (N = 1, or β when counting samples), so with α = 1/N every frame
    weighs the same, as the thesis's sec. 2.4.5 says of α = 1/N (an average over all
    samples); the fresh colour is this frame's own input, not an earlier sample."""
    return jnp.concatenate([s, jnp.zeros(s.shape[:-1] + (1,), s.dtype)], -1)


def init_state(frame: Frame, config: Config = Config()) -> State:
    color = frame.color.astype(jnp.float32)
    s, _ = _scaled_input(config, color, _jau_coords(frame, config.factor))
    return State(_fresh(s))


def step(params, state: State, frame: Frame, config: Config = Config()):
    f = config.factor
    color = frame.color.astype(jnp.float32)
    depth = frame.depth.astype(jnp.float32)
    motion = frame.motion.astype(jnp.float32)
    # The named scopes label the HLO for profiles (``Spec.stages``, python -m jtus.profile).
    with jax.named_scope("input_upsampling"):
        xy = _jau_coords(frame, f)
        s, beta_max = _scaled_input(config, color, xy)
        fresh = _fresh(s)
    history = state.history
    with jax.named_scope("reprojection"):
        mv = sampling.dilate_motion(motion, depth) if config.dilation else motion
        pos = sampling.reproject_coords(mv, f)
        # Colour and count are read by separate warps (the same values): XLA:CPU splits
        # one 16-tap read whose result feeds two consumers into per-tap gathers several
        # times slower than the whole read (docs/performance.md).
        rep, inside = sampling.sample(history[..., :3], pos, config.warp, a=config.warp_a,
                                      return_mask=True)
        # a reset frame's history is the fresh input, unwarped (base.reset_select)
        rep = reset_select(frame.reset, fresh[..., :3], jnp.where(inside, rep, fresh[..., :3]))
        rep_count = sampling.sample(history[..., 3:], pos, config.warp, a=config.warp_a)
        count = reset_select(frame.reset, fresh[..., 3:],
                             jnp.where(inside, rep_count, fresh[..., 3:]))
    with jax.named_scope("rectification"):
        rgb = _rectify(config, rep, color, xy)
    with jax.named_scope("output"):
        beta = _beta(config, frame, beta_max)
        count = count + (1.0 if config.count == "frames" else beta)
        # N = 0 (a pixel no sample reached yet, counting samples): 1/0 = inf, clipped to 1
        alpha = (jnp.clip(1.0 / count, config.alpha, 1.0) if config.inverse_count
                 else config.alpha)
        ab = alpha * beta
        out = ab * s + (1 - ab) * rgb
        new = State(jnp.concatenate([out, count], -1))
    return out, new


def make(config: Config = Config()) -> Model:
    return bind(config, step, init_state=init_state)


def cost(config: Config, H, W) -> Cost:
    px = H * W
    lr = px // (config.factor ** 2)
    scaled = px * (3 * 4 * 2 if config.filter == "tent" else 9 * (3 * 2 + 8))
    warp = px * (sampling.TAPS[config.warp] * 4 * 2 + 20)
    rect = 0 if config.rectify == "none" else px * 9 * 3 * 3
    blend = px * 12
    compulsory = 4 * (lr * 6 + 2 * px * 4 + px * 3)
    return Cost(scaled + warp + rect + blend, 0.0, compulsory, compulsory)


STAGES = ("input_upsampling", "reprojection", "rectification", "output")


def _stages(config: Config):
    """The stages a config's step labels: no rectification where it has none."""
    return tuple(s for s in STAGES if s != "rectification" or config.rectify != "none")


SPECS = tuple(Spec(name, make, preset, cost, stages=_stages(preset(2)))
              for name, preset in PRESETS.items())
