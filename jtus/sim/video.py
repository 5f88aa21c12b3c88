"""Rendering whole videos: jittered 1-spp inputs per factor and supersampled targets."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jtus.frame import Frame
from jtus.sampling import halton, jitter_sequence
from jtus.sim import paths, render, walk
from jtus.sim.mesh import MeshRenderer, MeshScene
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


# Four cells of the 4x4 stratified grid, one in each row and each column (the rotated-
# grid pattern): adaptive targets' first pass, completed to the whole grid where refined
ROTATED_GRID = np.array([(0.125, 0.375), (0.375, 0.875), (0.625, 0.125), (0.875, 0.625)])
_GRID16_REST = np.array([o for o in subsample_offsets(16).tolist()
                         if o not in ROTATED_GRID.tolist()])
# the cheapest of those tried that beat uniform 16 samples on every train frame and train
# level (docs/results/adaptive-targets-train/)
ADAPTIVE_THRESHOLDS = (1 / 32, 1 / 16)
TARGETS = ("uniform", "adaptive")


def _spread(samples):
    """Per pixel, the largest range over samples ``[S,N,3]`` of a tone-mapped channel
    (``x / (1 + x)``: HDR highlights do not dominate)."""
    t = samples / (1.0 + samples)
    return (t.max(0) - t.min(0)).max(-1)


def _grow(busy):
    """``busy [H,W]`` and its 8 neighbours, flattened: an edge between two pixels' samples
    may leave one of them uniform."""
    grown = busy.copy()
    grown[1:] |= busy[:-1]
    grown[:-1] |= busy[1:]
    grown[:, 1:] |= grown[:, :-1].copy()
    grown[:, :-1] |= grown[:, 1:].copy()
    return grown.reshape(-1)


def _morton(x, y):
    """Z-order (Morton) codes of non-negative integer pixel coordinates below 2**16."""
    def spread(v):
        v = np.asarray(v, np.uint64)
        for shift, mask in ((8, 0x00FF00FF), (4, 0x0F0F0F0F), (2, 0x33333333),
                            (1, 0x55555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v
    return spread(x) | (spread(y) << np.uint64(1))


CHUNK = 16384


class VideoRenderer:
    """Renders the frames of a scene; compiles the scene's renderer once. A
    ``MeshScene`` is cast by ``jtus.sim.mesh.MeshRenderer`` along ``jtus.sim.walk``'s
    camera paths; everything else (jitter, targets, holds) is the same. ``intersect``:
    how the analytic renderer meets objects (``jtus.sim.render.make_split_renderer``;
    ``"culled"``, the default, skips objects no ray of a tile can reach). ``targets``:
    ``"uniform"`` (``spp`` samples in every pixel) or ``"adaptive"``
    (``adaptive_target``; ``spp`` then unused)."""

    def __init__(self, scene: Scene, size, factors=(2, 4), spp=16, spp_match=1,
                 intersect="culled", targets="uniform"):
        if targets not in TARGETS:
            raise ValueError(f"targets: expected one of {TARGETS}, got {targets!r}")
        self.scene = scene
        self.targets = targets
        self.H, self.W = size
        for f in factors:
            if self.H % f or self.W % f:
                raise ValueError(f"size: {self.H}x{self.W} is not divisible by factor {f}")
        self.factors = tuple(factors)
        self.spp = spp
        self.spp_match = spp_match
        self.offsets = subsample_offsets(spp)
        # Every call renders CHUNK rays (the last chunk padded): one compilation per
        # scene serves the inputs of every factor and the target.
        self.chunk = min(CHUNK, self.H * self.W)
        if isinstance(scene, MeshScene):
            self._mesh = MeshRenderer(scene)
        else:
            self._mesh = None
            # colour for every point, depth and motion only where asked (the inputs):
            # the supersampled targets need colour alone
            self._shade, self._geometry = render.make_split_renderer(scene, intersect)

    def timeline(self, split, index, length):
        """The per-frame states of one video."""
        if self._mesh is not None:
            return walk.timeline(self._mesh, split, index, length, self.W / self.H)
        return paths.timeline(self.scene, split, index, length, self.W / self.H)

    def _cast(self, state: paths.FrameState, xy, color_only=False):
        """Render normalized screen points ``[N,2]`` in fixed-size chunks: a dict of
        ``[N,...]`` numpy arrays; ``color`` alone with ``color_only`` (a mesh scene's
        caster computes all three either way)."""
        if self._mesh is not None:
            out = {}
            for i in range(0, len(xy), self.chunk):
                part = self._mesh.cast(state, xy[i:i + self.chunk], self.pixel_angle(state))
                for k, v in part.items():
                    out.setdefault(k, []).append(v)
            return {k: np.concatenate(v) for k, v in out.items()}
        n, c = len(xy), self.chunk
        pad = -n % c
        xy = np.concatenate([np.asarray(xy, np.float32), np.full((pad, 2), 0.5, np.float32)])
        arr = render.state_arrays(state)
        angle = self.pixel_angle(state)
        parts = []
        for i in range(0, len(xy), c):
            pts = jnp.asarray(xy[i:i + c])
            color, t, obj = self._shade(arr, pts, angle)
            parts.append({"color": color} if color_only else
                         {"color": color, **self._geometry(arr, pts, t, obj)})
        return {k: np.concatenate([np.asarray(p[k]) for p in parts])[:n] for k in parts[0]}

    def pixel_angle(self, state: paths.FrameState):
        return render.pixel_angle(state.camera.tan_half[1], self.H, self.spp_match)

    def input(self, state: paths.FrameState, factor, jitter):
        """One 1-spp input at ``H/f x W/f``: color, depth, motion (LR pixels)."""
        h, w = self.H // factor, self.W // factor
        jx, jy = _grid(h, w)
        xy = np.stack([(jx + jitter[0]) / w, (jy + jitter[1]) / h], -1)
        out = self._cast(state, xy)
        return (out["color"].reshape(h, w, 3), out["depth"].reshape(h, w, 1),
                (out["motion"] * np.array([w, h], np.float32)).reshape(h, w, 2))

    def points(self, state, xy):
        """Render arbitrary normalized screen points ``[N,2]`` (one sample each)."""
        return self._cast(state, xy)

    def _box(self, state, pixels, offsets):
        """Box-filtered colour ``[len(pixels),3]`` (float64) of flat pixel indices, one
        sample at each of ``offsets [S,2]`` inside each pixel; and the samples
        ``[S,len(pixels),3]``.

        The samples are cast block by block: each bundle of the renderer
        (``render.BUNDLE`` rays) takes every sample of ``BUNDLE // S`` pixels that are
        consecutive along a Z-order curve (an aligned square tile when ``pixels`` is the
        whole frame; a compact patch of a sparse set), so that its rays see few objects
        and few texture kinds, which the renderer then skips. A block short of a whole
        bundle repeats its first ray, so that no bundle straddles two blocks."""
        S, n = len(offsets), len(pixels)
        bundle = min(self.chunk, render.BUNDLE)
        per_call = max(1, bundle // S)
        width = -(-S * per_call // bundle) * bundle  # rays per block, whole bundles
        py, px = np.divmod(pixels, self.W)
        order = np.argsort(_morton(px, py), kind="stable")
        slots = np.full(-(-n // per_call) * per_call, -1)
        slots[:n] = order
        blocks = slots.reshape(-1, 1, per_call)
        filled = np.where(blocks >= 0, blocks, blocks[..., :1])  # slot 0 is always used
        off = np.asarray(offsets, np.float64)[None, :, None]
        xy = np.stack([(px[filled] + off[..., 0]) / self.W,
                       (py[filled] + off[..., 1]) / self.H], -1).reshape(len(blocks), -1, 2)
        xy = np.concatenate([xy, np.repeat(xy[:, :1], width - xy.shape[1], 1)], 1)
        cast = self._cast(state, xy.reshape(-1, 2).astype(np.float32), color_only=True)
        cast = cast["color"].reshape(len(blocks), width, 3)[:, :S * per_call]
        cast = cast.reshape(len(blocks), S, per_call, 3).transpose(1, 0, 2, 3).reshape(S, -1, 3)
        col = np.empty((S, n, 3), np.float32)
        col[:, order] = cast[:, :n]
        return col.mean(0, dtype=np.float64), col

    def target(self, state: paths.FrameState):
        """The box-filtered target at ``H x W``: ``spp`` samples on a stratified grid in
        every pixel, or with ``targets="adaptive"`` the ``adaptive_target``."""
        if self.targets == "adaptive":
            return self.adaptive_target(state)[0]
        pixels = np.arange(self.H * self.W)
        col, _ = self._box(state, pixels, self.offsets)
        return col.astype(np.float32).reshape(self.H, self.W, 3)

    def adaptive_target(self, state, thresholds=ADAPTIVE_THRESHOLDS):
        """A target that spends samples where they disagree, in three passes:
        ``ROTATED_GRID``'s 4 samples in every pixel; where their range on any
        tone-mapped channel exceeds ``thresholds[0]`` (and in those pixels' 8
        neighbours), the 12 samples that complete the 4x4 grid, so that the pixel is
        the uniform 16-sample target's; where those 16 exceed ``thresholds[1]``, an 8x8
        grid of 64 fresh samples. Returns ``(target [H,W,3], samples [H,W])``: each
        pixel's count of samples averaged (4, 16 or 64; the rays cast are that, plus
        16 where it is 64). ``experiments/adaptive_targets.py`` measures it against
        64-sample references whose sample positions neither pattern shares
        (``jittered_reference``; docs/simulator.md)."""
        n = self.H * self.W
        col, s4 = self._box(state, np.arange(n), ROTATED_GRID)
        count = np.full(n, 4)
        mid = np.flatnonzero(_grow((_spread(s4) > thresholds[0]).reshape(self.H, self.W)))
        if len(mid):
            c12, s12 = self._box(state, mid, _GRID16_REST)
            col[mid] = (4 * col[mid] + 12 * c12) / 16
            count[mid] = 16
            hard = mid[_spread(np.concatenate([s4[:, mid], s12])) > thresholds[1]]
            if len(hard):
                col[hard], _ = self._box(state, hard, subsample_offsets(64))
                count[hard] = 64
        return (col.astype(np.float32).reshape(self.H, self.W, 3),
                count.reshape(self.H, self.W))

    def jittered_reference(self, state, cells, seed=0):
        """A reference target to measure others against: ``cells x cells`` samples per
        pixel, one at a uniformly random point of each cell, drawn anew in every pixel
        (so it shares no sample position with a grid pattern, nor a grid's aliasing of
        periodic detail), box-filtered; float64 ``[H,W,3]``."""
        rng = np.random.default_rng(seed)
        jy, jx = np.divmod(np.arange(self.H * self.W, dtype=np.float64), self.W)
        acc = np.zeros((self.H * self.W, 3))
        for a in range(cells):
            for b in range(cells):
                o = rng.random((self.H * self.W, 2))
                xy = np.stack([(jx + (a + o[:, 0]) / cells) / self.W,
                               (jy + (b + o[:, 1]) / cells) / self.H], -1)
                acc += self._cast(state, xy.astype(np.float32), color_only=True)["color"]
        return (acc / cells ** 2).reshape(self.H, self.W, 3)

    def video(self, split, index, length, progress=None, jitter="thesis", jitter_phase=0,
              hold_from=None):
        """A dict: ``target [T,H,W,3]``, ``reset [T]``, and per factor ``x{f}`` a dict
        of ``color``, ``depth``, ``motion``, ``jitter``; ``exposure [T]`` too with ``hdr``.
        ``jitter`` names the sequence
        (``jtus.sampling.jitter_sequence``); frame t uses element ``t + jitter_phase``.

        ``hold_from``: from this frame on the scene stands still at the state of the
        frame before (camera, objects, lights, time), so only the jitter moves and the
        motion is zero: a static hold after a moving start. Its target is rendered once
        and each distinct jitter position's input once."""
        moving = length if hold_from is None else max(1, min(hold_from, length))
        states = self.timeline(split, index, moving)
        out = {"target": [], "reset": [], "exposure": [],
               **{f"x{f}": {"color": [], "depth": [], "motion": [], "jitter": []}
                  for f in self.factors}}
        seqs = {f: jitter_sequence(jitter, f) for f in self.factors}
        held = {}  # (factor, jitter) -> the held state's input
        for t in range(length):
            st, still = states[min(t, moving - 1)], t >= moving
            if not still:
                target = self.target(st)  # the last moving frame's is the held one
            out["target"].append(target)
            out["reset"].append(t == 0 or (st.cut and not still))
            out["exposure"].append(st.exposure)
            for f in self.factors:
                jit = seqs[f][(t + jitter_phase) % len(seqs[f])]
                key = (f, tuple(jit))
                if still and key not in held:
                    c, d, m = self.input(st, f, jit)
                    held[key] = (c, d, np.zeros_like(m))
                c, d, m = held[key] if still else self.input(st, f, jit)
                g = out[f"x{f}"]
                g["color"].append(c)
                g["depth"].append(d)
                g["motion"].append(m)
                g["jitter"].append(jit.astype(np.float32))
            if progress is not None:
                progress(1)
        res = {"target": np.stack(out["target"]).astype(np.float32),
               "reset": np.array(out["reset"], bool)}
        if self.scene.has("hdr"):
            res["exposure"] = np.array(out["exposure"], np.float32)
        for f in self.factors:
            res[f"x{f}"] = {k: np.stack(v).astype(np.float32) for k, v in out[f"x{f}"].items()}
        return res


def render_video(scene: Scene, split, index, length, size=(128, 128), factors=(2, 4), spp=16,
                 spp_match=1):
    return VideoRenderer(scene, size, factors, spp, spp_match).video(split, index, length)


def static_hold(scene: Scene, size, factor, jitter, length, spp=16, split="test",
                renderer=None):
    """A hold: the first frame of ``scene``'s video, unchanged for ``length`` frames,
    sampled with jitter sequence ``jitter``; zero motion, reset on frame 0 only.

    Returns ``(Frame [T,1,...] numpy, targets [T,1,H,W,3])``. Only the distinct jitter
    positions are rendered (a hold is the hard case of convergence: whatever a
    temporal up-sampler shows after the jitter cycle is its steady state).
    ``renderer``: a ``VideoRenderer`` of this scene to reuse (one compilation for many
    holds); its size and spp then apply."""

    r = renderer or VideoRenderer(scene, (size, size), (factor,), spp)
    v = r.video(split, 0, length, jitter=jitter, hold_from=1)
    x = v[f"x{factor}"]
    reset = np.zeros((length, 1), bool)
    reset[0] = True
    frame = Frame(x["color"][:, None], x["depth"][:, None],
                  np.zeros(x["color"].shape[:-1] + (2,), np.float32)[:, None],
                  x["jitter"][:, None], reset)
    return frame, v["target"][:, None]


__all__ = ["VideoRenderer", "render_video", "static_hold", "subsample_offsets"]
