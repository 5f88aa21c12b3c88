"""Rendering whole videos: jittered 1-spp inputs per factor and supersampled targets."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jtus.sampling import halton, jitter_sequence
from jtus.sim import paths, render
from jtus.sim.scene import Scene


def subsample_offsets(spp):
    """Positions inside a pixel for ``spp`` samples: a stratified grid when spp is a
    square, Halton(2,3) otherwise. ``[spp,2]`` in [0,1)^2."""
    if spp < 1:
        raise ValueError(f"spp: expected >= 1, got {spp}")
    n = math.isqrt(spp)
    if n * n == spp:
        g = (np.arange(n) + 0.5) / n
        return np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
    return halton(spp)


def _grid(h, w):
    i, j = np.mgrid[0:h, 0:w].astype(np.float32)
    return j.reshape(-1), i.reshape(-1)


class VideoRenderer:
    """Renders the frames of a scene; compiles the scene's renderer once."""

    def __init__(self, scene: Scene, size, factors=(2, 4), spp=16, spp_match=1):
        self.scene = scene
        self.H, self.W = size
        for f in factors:
            if self.H % f or self.W % f:
                raise ValueError(f"size: {self.H}x{self.W} is not divisible by factor {f}")
        self.factors = tuple(factors)
        self.spp = spp
        self.spp_match = spp_match
        self._input = render.make_renderer(scene, motion=True)
        self._target = render.make_renderer(scene, motion=False)
        self.offsets = subsample_offsets(spp)

    def pixel_angle(self, state: paths.FrameState):
        return render.pixel_angle(state.camera.tan_half[1], self.H, self.spp_match)

    def input(self, state: paths.FrameState, factor, jitter):
        """One 1-spp input at ``H/f x W/f``: color, depth, motion (LR pixels)."""
        h, w = self.H // factor, self.W // factor
        jx, jy = _grid(h, w)
        xy = np.stack([(jx + jitter[0]) / w, (jy + jitter[1]) / h], -1)
        out = self._input(render.state_arrays(state), jnp.asarray(xy), self.pixel_angle(state))
        return (np.asarray(out["color"]).reshape(h, w, 3),
                np.asarray(out["depth"]).reshape(h, w, 1),
                (np.asarray(out["motion"]) * np.array([w, h], np.float32)).reshape(h, w, 2))

    def points(self, state, xy):
        """Render arbitrary normalized screen points ``[N,2]`` (one sample each)."""
        return self._input(render.state_arrays(state), jnp.asarray(xy, jnp.float32),
                           self.pixel_angle(state))

    def target(self, state: paths.FrameState):
        """The ``spp``-sample box-filtered target at ``H x W``."""
        jx, jy = _grid(self.H, self.W)
        arr = render.state_arrays(state)
        angle = self.pixel_angle(state)
        acc = 0.0
        for ox, oy in self.offsets:
            xy = np.stack([(jx + ox) / self.W, (jy + oy) / self.H], -1)
            acc = acc + self._target(arr, jnp.asarray(xy, jnp.float32), angle)["color"]
        return np.asarray(acc / len(self.offsets)).reshape(self.H, self.W, 3)

    def video(self, split, index, length, progress=None):
        """A dict: ``target [T,H,W,3]``, ``reset [T]``, and per factor ``x{f}`` a dict
        of ``color``, ``depth``, ``motion``, ``jitter``."""
        states = paths.timeline(self.scene, split, index, length, self.W / self.H)
        out = {"target": [], "reset": [], **{f"x{f}": {"color": [], "depth": [], "motion": [],
                                                       "jitter": []} for f in self.factors}}
        seqs = {f: jitter_sequence("thesis", f) for f in self.factors}
        for t, st in enumerate(states):
            out["target"].append(self.target(st))
            out["reset"].append(t == 0 or st.cut)
            for f in self.factors:
                jit = seqs[f][t % len(seqs[f])]
                c, d, m = self.input(st, f, jit)
                g = out[f"x{f}"]
                g["color"].append(c)
                g["depth"].append(d)
                g["motion"].append(m)
                g["jitter"].append(jit.astype(np.float32))
            if progress is not None:
                progress(1)
        res = {"target": np.stack(out["target"]).astype(np.float32),
               "reset": np.array(out["reset"], bool)}
        for f in self.factors:
            res[f"x{f}"] = {k: np.stack(v).astype(np.float32) for k, v in out[f"x{f}"].items()}
        return res


def render_video(scene: Scene, split, index, length, size=(128, 128), factors=(2, 4), spp=16,
                 spp_match=1):
    return VideoRenderer(scene, size, factors, spp, spp_match).video(split, index, length)


__all__ = ["VideoRenderer", "render_video", "subsample_offsets"]
