"""The one ``lax.scan`` helper: every model, every training, evaluation and benchmark
path runs a model's ``step`` through here (after jax-cfd's ``trajectory``).

Sequences are time-major: ``frames`` is a ``jtus.Frame`` whose fields are
``[T,B,...]``, ``targets`` is ``[T,B,H,W,3]``.

Training losses see, for each frame, the previous output and target (temporal losses
warp them to the current frame); they travel in ``Carry`` next to the model state,
so that truncated BPTT windows chain exactly.

Modes:
- ``outputs``: no-gradient evaluation rollout, the stacked outputs.
- ``metrics``: a per-frame reduction instead of the outputs (long videos).
- ``window_loss``: loss averaged over the last ``loss_frames`` frames of a window,
  differentiable through the whole window (BPTT; the thesis uses 5 of 30).
- ``tbptt_windows``: the static window plan of truncated BPTT (k1, k2): an update
  every k1 frames, each back-propagating through the last k2 frames; the carry
  between windows is cut with ``stop_gradient``. With ``k2 = T`` it is BPTT.

``remat`` wraps the step in ``jax.checkpoint``: ``True`` saves nothing (every
intermediate is recomputed in the backward pass), a name from ``REMAT_POLICIES``
saves what that ``jax.checkpoint_policies`` policy saves; in ``window_loss``,
``"reverse"`` is a hand-written reverse-time backward (``_segment_reverse``) that
stacks only each frame's carry and recomputes one step at a time. ``unroll`` is
passed to ``lax.scan`` (``True`` unrolls fully: on XLA:CPU a rolled scan over
convolutions has a slow backward, see ``docs/performance.md``).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jtus.frame import validate


class Carry(NamedTuple):
    state: Any              # the model's state
    prev_out: jax.Array     # [B,H,W,3] the previous frame's output
    prev_target: jax.Array  # [B,H,W,3] the previous frame's target
    has_prev: jax.Array     # [] bool: False at the start of a video


def start(state, target_like) -> Carry:
    """The carry at the start of a video (no previous frame)."""
    def zeros():  # two buffers: the carry may be donated
        return jnp.zeros(target_like.shape, jnp.float32)

    return Carry(state, zeros(), zeros(), jnp.asarray(False))


def first_state(model, frames):
    """The model's state for the first frame of time-major ``frames`` (its
    ``init_state``): where every rollout over a video starts."""
    return model.init_state(jax.tree_util.tree_map(lambda x: x[0], frames))


REMAT_POLICIES = {
    "dots": jax.checkpoint_policies.dots_saveable,  # matmul and convolution outputs
    "dots_no_batch": jax.checkpoint_policies.dots_with_no_batch_dims_saveable,
}


def _body(step, params, remat):
    if remat in (False, None):
        fn = step
    elif remat is True:
        fn = jax.checkpoint(step)
    elif remat in REMAT_POLICIES:
        fn = jax.checkpoint(step, policy=REMAT_POLICIES[remat])
    else:
        raise ValueError(f"remat: expected True, False or one of {tuple(REMAT_POLICIES)}, "
                         f"got {remat!r}")
    return lambda state, frame: fn(params, state, frame)


def _check(frames, check, state=None):
    """The API boundary: reject malformed or non-finite inputs with a clear error, and a
    state whose batch is not the frames' (it would broadcast silently). Skipped when
    ``check`` is False or inside a trace (jitted hot loops)."""
    if check and not any(isinstance(x, jax.core.Tracer)
                         for x in jax.tree_util.tree_leaves((frames, state))):
        validate(frames, time_major=True, check_finite=True)
        batch = np.shape(frames.color)[1]
        for leaf in jax.tree_util.tree_leaves(state):
            if np.ndim(leaf) >= 1 and np.shape(leaf)[0] != batch:
                raise ValueError(f"state: expected a batch of {batch} (the frames'), got a "
                                 f"state array of shape {tuple(np.shape(leaf))}")


def outputs(step, params, state, frames, *, remat=False, unroll=1, check=True):
    """Scan ``step`` over ``frames``; returns ``(outs [T,B,H,W,3], final state)``.
    ``check``: validate concrete inputs first (NaN/Inf, shapes); see ``_check``."""
    _check(frames, check, state)
    body = _body(step, params, remat)

    def f(s, frame):
        out, s = body(s, frame)
        return s, out

    state, outs = jax.lax.scan(f, state, frames, unroll=unroll)
    return outs, state


def video(model, params, frames, *, check=True):
    """A model's outputs ``[T,B,H,W,3]`` over a whole video of time-major ``frames``,
    from its first state (``first_state``), compiled: what evaluation, figures and the
    ``upsample`` CLI run. Compiled once per model and input shape (the model is a
    static argument), so many videos of one size through one model share a program."""
    _check(frames, check)
    return _video(model, params, frames)


@functools.partial(jax.jit, static_argnums=0)
def _video(model, params, frames):
    return outputs(model.step, params, first_state(model, frames), frames, check=False)[0]


def metrics(step, params, state, frames, targets, metric_fn, *, unroll=1, check=True):
    """Scan and reduce each frame with
    ``metric_fn(out, target, prev_out, prev_target, has_prev, frame) -> pytree``
    (the previous frame's output and target are carried, for temporal metrics);
    returns ``(per-frame metrics stacked over T, final state)``; no outputs kept."""
    _check(frames, check, state)
    body = _body(step, params, False)

    def f(c, xs):
        frame, target = xs
        out, s = body(c.state, frame)
        m = metric_fn(out, target, c.prev_out, c.prev_target, c.has_prev, frame)
        return Carry(s, out.astype(jnp.float32), target.astype(jnp.float32),
                     jnp.asarray(True)), m

    carry, ms = jax.lax.scan(f, start(state, targets[0]), (frames, targets), unroll=unroll)
    return ms, carry.state


def parts(model):
    """``(advance, prepare)`` of a ``Model`` for ``window_loss`` (``Model``'s docstring);
    ``(step, None)`` for a model without the split."""
    if model.advance is None:
        return model.step, None
    return model.advance, model.prepare


def _segment(body, loss_fn, carry, frames, prepared, targets, with_loss, unroll):
    def f(c, xs):
        frame, pre, target = xs
        out, state = body(c.state, frame if pre is None else pre)
        with jax.named_scope("loss"):
            loss = (loss_fn(out, target, c.prev_out, c.prev_target, c.has_prev, frame)
                    if with_loss else jnp.zeros((), jnp.float32))
        return Carry(state, out.astype(jnp.float32), target.astype(jnp.float32),
                     jnp.asarray(True)), loss

    return jax.lax.scan(f, carry, (frames, prepared, targets), unroll=unroll)


def _zero_cotangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def _segment_reverse(step, loss_fn, params, carry, frames, prepared, targets, with_loss):
    """``_segment`` (no remat, no unroll) with a hand-written backward pass: the
    forward scan keeps only each frame's incoming carry; the backward is a reverse-time
    scan that recomputes one frame's step under ``jax.vjp`` at a time, so no
    intermediate of the step is stacked over frames (``remat="reverse"``; equal to
    autodiff: ``tests/test_rollout.py``)."""
    def frame_fn(p, c, xs):
        frame, pre, target = xs
        out, state = step(p, c.state, frame if pre is None else pre)
        loss = (loss_fn(out, target, c.prev_out, c.prev_target, c.has_prev, frame)
                if with_loss else jnp.zeros((), jnp.float32))
        return Carry(state, out.astype(jnp.float32), target.astype(jnp.float32),
                     jnp.asarray(True)), loss

    def split(c):  # the differentiable part of a carry, and its flag
        return c._replace(has_prev=None), c.has_prev

    @jax.custom_vjp
    def seg(p, c, xs):
        return jax.lax.scan(lambda c, x: frame_fn(p, c, x), c, xs)

    def fwd(p, c, xs):
        def f(c, x):
            c2, loss = frame_fn(p, c, x)
            return c2, (loss, split(c)[0], c.has_prev)

        last, (ls, cs, flags) = jax.lax.scan(f, c, xs)
        return (last, ls), (p, cs, flags, xs)

    def bwd(res, ct):
        p, cs, flags, xs = res
        ct_last, ct_ls = ct
        ct_c = split(ct_last)[0]

        def b(acc, inp):
            g, ct_c = acc
            cf, flag, x, ct_l = inp

            def f(p, cf):
                c2, loss = frame_fn(p, cf._replace(has_prev=flag), x)
                return split(c2)[0], loss

            _, vjp = jax.vjp(f, p, cf)
            dp, dc = vjp((ct_c, ct_l))
            return (jax.tree_util.tree_map(jnp.add, g, dp), dc), None

        zeros = jax.tree_util.tree_map(jnp.zeros_like, p)
        (g, ct_c0), _ = jax.lax.scan(b, (zeros, ct_c), (cs, flags, xs, ct_ls), reverse=True)
        ct_flag = _zero_cotangent(flags[0])
        return g, ct_c0._replace(has_prev=ct_flag), jax.tree_util.tree_map(_zero_cotangent, xs)

    seg.defvjp(fwd, bwd)
    return seg(params, carry, (frames, prepared, targets))


def window_loss(step, loss_fn, params, carry: Carry, frames, targets, *, loss_frames,
                keep_at=None, remat=False, unroll=1, prepare=None, late=None):
    """Mean of ``loss_fn`` over the last ``loss_frames`` frames of the window.

    ``loss_fn(out, target, prev_out, prev_target, has_prev, frame) -> scalar``.
    ``late``: ``(index, late_fn)``: frames of the window from ``index`` on are scored
    by ``late_fn`` instead (a loss that changes along a long sequence, e.g. a temporal
    term weighted up once a static hold has had time to converge).
    Returns ``(loss, (final carry, carry after keep_at frames or None))``. Segments
    are cut at static indices, so frames before the loss frames compute no loss.

    ``prepare``: a model's ``prepare`` (with its ``advance`` as ``step``; ``parts``),
    run on every frame of the window at once before the scan, so that what does not
    recur is neither computed inside the loop nor saved per frame for the backward
    pass (a training window is short; long inference rollouts keep the plain step).
    """
    n = frames.color.shape[0]
    if not 1 <= loss_frames <= n:
        raise ValueError(f"loss_frames: expected 1..{n} (the window length), got {loss_frames}")
    if keep_at is not None and not 0 < keep_at <= n:
        raise ValueError(f"keep_at: expected 1..{n}, got {keep_at}")
    late_at, late_fn = late if late is not None else (n, None)
    if not 0 <= late_at <= n:
        raise ValueError(f"late: expected a first frame in 0..{n}, got {late_at}")
    reverse = remat == "reverse"
    if reverse and unroll != 1:
        raise ValueError(f"unroll: remat='reverse' scans one frame at a time forward and "
                         f"back; expected 1, got {unroll}")
    body = None if reverse else _body(step, params, remat)
    # frames before the loss frames score nothing: the late loss cuts only inside them
    cuts = sorted({0, n - loss_frames, n, max(late_at, n - loss_frames)}
                  | ({keep_at} if keep_at else set()))
    total, kept = jnp.zeros((), jnp.float32), None
    for a, b in zip(cuts[:-1], cuts[1:]):
        seg_frames, seg_targets = jax.tree_util.tree_map(lambda x: x[a:b], (frames, targets))
        prepared = None
        if prepare is not None:  # per segment: slicing prepared HR tensors costs copies
            with jax.named_scope("prepare"):
                prepared = jax.vmap(prepare)(seg_frames)
        fn = late_fn if a >= late_at else loss_fn
        if reverse:
            carry, losses = _segment_reverse(step, fn, params, carry, seg_frames, prepared,
                                             seg_targets, with_loss=a >= n - loss_frames)
        else:
            carry, losses = _segment(body, fn, carry, seg_frames, prepared, seg_targets,
                                     with_loss=a >= n - loss_frames, unroll=unroll)
        total = total + losses.sum()
        if b == keep_at:
            kept = carry
    return total / loss_frames, (carry, kept)


class Window(NamedTuple):
    start: int  # first frame of the window
    stop: int   # one past the last frame; the loss covers [stop - k1, stop)


def tbptt_windows(length, k1, k2):
    """The windows of TBPTT(k1, k2) over a sequence of ``length`` frames.

    Windows all have k2 frames (one trace of the train step); the first ends at k2,
    each next one k1 frames later, and starts from the carry after the first k1
    frames of the previous one. Requires ``1 <= k1 <= k2 <= length`` and
    ``(length - k2) % k1 == 0`` so that every frame after the first window is
    trained on exactly once.
    """
    if not 1 <= k1 <= k2 <= length:
        raise ValueError(f"tbptt: expected 1 <= k1 <= k2 <= sequence length, "
                         f"got k1={k1}, k2={k2}, length={length}")
    if (length - k2) % k1:
        raise ValueError(f"tbptt: (length - k2) = {length - k2} must be a multiple of "
                         f"k1 = {k1}")
    return [Window(s, s + k2) for s in range(0, length - k2 + 1, k1)]
