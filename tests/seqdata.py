"""Shared test helpers: frames with given motion, small synthetic sequences (smooth
images, sub-pixel motion, jitter from the thesis patterns; not a renderer, just
well-conditioned inputs), time-step selection, TBPTT gradients window by window, and
experiment scripts loaded as modules."""

import importlib.util
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from jtus import rollout
from jtus.frame import Frame
from jtus.sampling import jitter_sequence


def frame_with_motion(motion):
    """A ``Frame`` of black colour and depth with LR ``motion [B,h,w,2]`` and centred
    jitter: what the temporal losses read of a frame (its motion)."""
    b, h, w, _ = motion.shape
    return Frame(jnp.zeros((b, h, w, 3)), jnp.zeros((b, h, w, 1)), jnp.asarray(motion),
                 jnp.full((b, 2), 0.5))


def _smooth(rng, shape, lo=0.0, hi=1.0, k=3):
    """[...,h,w,c] sums of a few random low-frequency sinusoids mapped into [lo,hi]."""
    *lead, h, w, c = shape
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    out = np.zeros(shape)
    for _ in range(k):
        fx, fy = rng.uniform(0.5, 3, size=2)
        ph = rng.uniform(0, 2 * np.pi, size=tuple(lead) + (1, 1, c))
        out += np.sin(2 * np.pi * (fx * xx + fy * yy)[..., None] + ph)
    out = (out / k + 1) / 2
    return lo + (hi - lo) * out


def sequence(T=10, B=2, h=8, w=8, factor=4, seed=0, dtype=np.float32, max_motion=0.8,
             reset_at=None):
    """Time-major ``Frame`` of [T,B,...] numpy arrays and targets [T,B,H,W,3]."""
    rng = np.random.default_rng(seed)
    color = _smooth(rng, (T, B, h, w, 3))
    depth = _smooth(rng, (T, B, h, w, 1), 0.3, 0.99)
    motion = (_smooth(rng, (T, B, h, w, 2)) * 2 - 1) * max_motion
    seq = jitter_sequence("thesis", factor)
    offset = rng.integers(0, len(seq), size=B)
    jitter = np.stack([seq[(t + offset) % len(seq)] for t in range(T)])
    reset = np.zeros((T, B), bool)
    if reset_at is not None:
        t, b = reset_at
        reset[t, b] = True
    targets = _smooth(rng, (T, B, h * factor, w * factor, 3))
    frames = Frame(*(x.astype(dtype) for x in (color, depth, motion, jitter)), reset)
    return frames, targets.astype(dtype)


def to_jax(tree):
    import jax
    return jax.tree_util.tree_map(jnp.asarray, tree)


def jau_positions(jitter, h, w, f):
    """Where jitter-aligned up-sampling reads an ``h`` x ``w`` LR image for each HR pixel,
    ``[N,f*h,f*w,2]`` (x, y) in LR pixel coordinates (pixel i's centre at i + 0.5): the
    HR centre (X + 0.5) / f minus the jitter plus half a pixel (thesis sec. 4.1.1).
    Jitter 0.5 gives plain up-sampling's positions."""
    Y, X = np.mgrid[0:h * f, 0:w * f] + 0.5
    jitter = np.asarray(jitter, np.float64)
    return np.stack([X, Y], -1)[None] / f - jitter[:, None, None, :] + 0.5


def jau_reference(color, jitter, f):
    """Jitter-aligned bilinear up-sampling of ``color [N,h,w,C]`` with ``jitter [N,2]``,
    written out in numpy (float64) for the tests: HR pixel centre q = (x + 0.5) / f in
    LR coordinates; LR sample i sits at i + jitter (docs/conventions.md); bilinear
    between the two samples around q - jitter, indices clamped at the border. Jitter
    0.5 is plain bilinear up-sampling (``F.interpolate``, align_corners False)."""
    T, h, w, _ = color.shape
    jitter = np.asarray(jitter, np.float64)

    def axis(n, jit):
        t = (np.arange(n * f) + 0.5) / f - jit  # sample i is at i + jit: t indexes samples
        i0 = np.floor(t).astype(int)
        return np.clip(i0, 0, n - 1), np.clip(i0 + 1, 0, n - 1), t - i0

    out = np.zeros((T, h * f, w * f, color.shape[-1]))
    for k in range(T):
        y0, y1, ay = axis(h, jitter[k, 1])
        x0, x1, ax = axis(w, jitter[k, 0])
        c = np.asarray(color[k], np.float64)
        top = c[y0][:, x0] * (1 - ax)[None, :, None] + c[y0][:, x1] * ax[None, :, None]
        bot = c[y1][:, x0] * (1 - ax)[None, :, None] + c[y1][:, x1] * ax[None, :, None]
        out[k] = top * (1 - ay)[:, None, None] + bot * ay[:, None, None]
    return out


def first(tree):
    """Time step 0 of a time-major tree."""
    return jax.tree_util.tree_map(lambda x: x[0], tree)


def at(tree, t):
    """Time step ``t`` of a time-major tree."""
    return jax.tree_util.tree_map(lambda x: x[t], tree)


def tbptt_grads(step, loss_fn, params, carry, frames, targets, *, k1, k2, remat=False,
                unroll=1):
    """Gradients of every TBPTT window at fixed ``params``, each window's carry cut and
    handed on as ``jtus.train`` hands it. Returns ``([(loss, grads)], carry)``."""

    def f(p, c, fr, tg):
        return rollout.window_loss(step, loss_fn, p, c, fr, tg, loss_frames=k1,
                           keep_at=k1 if k1 < k2 else None, remat=remat, unroll=unroll)

    grad_fn = jax.jit(jax.value_and_grad(f, has_aux=True))
    results = []
    for w in rollout.tbptt_windows(frames.color.shape[0], k1, k2):
        sl = jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (frames, targets))
        (loss, (last, kept)), grads = grad_fn(params, carry, *sl)
        results.append((loss, grads))
        carry = jax.lax.stop_gradient(kept if kept is not None else last)
    return results, carry


def cast_frame(frame, dtype):
    """``frame`` with its colour, depth, motion and jitter in ``dtype``."""
    return frame._replace(**{k: jnp.asarray(getattr(frame, k), dtype)
                             for k in ("color", "depth", "motion", "jitter")})


def load_script(name, folder="experiments"):
    """An experiment script (or a tool) as a module, its folder on ``sys.path`` while
    it loads, as when it runs as a script."""
    where = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", folder)
    sys.path.insert(0, where)
    try:
        spec = importlib.util.spec_from_file_location(name, os.path.join(where, f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(where)
    return module
