"""``jtus.rollout``'s bookkeeping on a toy recurrent model that compiles in a fraction
of a second: every mode (``outputs``, ``metrics``, ``video``, ``window_loss`` with its
cuts, ``keep_at``, remat, unroll, hoisted preparation and the hand-written
reverse-time backward, ``tbptt_grads``) against a plain Python loop written here, in
float64, with gradients with respect to the parameters and to the incoming carry.

The DLCTUS tests in ``test_rollout.py`` check the same identities on the real network
(tens of seconds of compiling each); these run in seconds, so they are the focused
selection the mutation testing of ``jtus/rollout.py`` runs (``tools/mutation.py``).

The reference mirrors two choices of ``rollout``: the carried previous output and
target are float32 (a temporal loss reads them; a float64 model's carry is rounded),
and ``has_prev`` is False only before the first frame of a video.
"""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import rollout
from jtus.frame import Frame
from jtus.models.base import Model
from tests import seqdata

T, B, H, W = 6, 2, 3, 4


def _frames(seed=0, T=T, reset_at=((3, 1),), first=True):
    """``first``: the window starts a video (every element resets on frame 0); else it
    is the middle of one, whose incoming state matters."""
    rng = np.random.default_rng(seed)
    reset = np.zeros((T, B), bool)
    reset[0] = first
    for t, b in reset_at:
        reset[t, b] = True
    frames = Frame(color=rng.uniform(0.1, 0.9, (T, B, H, W, 3)),
                   depth=rng.uniform(0.2, 0.8, (T, B, H, W, 1)),
                   motion=rng.uniform(-1, 1, (T, B, H, W, 2)),
                   jitter=rng.uniform(0, 1, (T, B, 2)), reset=reset)
    targets = rng.uniform(0.1, 0.9, (T, B, H, W, 3))
    return jax.tree_util.tree_map(jnp.asarray, (frames, targets))


def _prepare(frame):
    # depends on neither parameters nor state; changes the fields the loss reads, so
    # a loss handed the prepared frame instead of the frame gives another value
    return frame._replace(color=2.0 * frame.color, depth=frame.depth + 1.0)


def _advance(p, h, pre):
    u = 0.5 * pre.color
    fresh = u * p["f"]
    h = jnp.where(pre.reset[:, None, None, None], fresh, h)  # a reset forgets the history
    h = jnp.tanh(p["a"] * h + p["b"] * u + p["c"] * (pre.depth - 1.0))
    return p["w"] * h + p["d"], h


def _step(p, h, frame):
    return _advance(p, h, _prepare(frame))


def _init_state(frame):
    return 0.25 * frame.color + 0.1  # reads the frame: the first one, not another


def _model(split):
    if split:
        return Model(init=None, init_state=_init_state, step=_step, config=None,
                     prepare=_prepare, advance=_advance)
    return Model(init=None, init_state=_init_state, step=_step, config=None)


def _params(seed=1):
    rng = np.random.default_rng(seed)
    return {k: jnp.asarray(rng.uniform(0.3, 0.9, (3,))) for k in "abcfw"} | {
        "d": jnp.asarray(rng.uniform(-0.1, 0.1, (3,)))}


def _loss(out, target, prev_out, prev_target, has_prev, frame):
    """Reads every argument: a spatial term, a temporal one on the previous frame's
    output and target, and one on the frame's depth."""
    spatial = jnp.mean((out - target) ** 2)
    temporal = jnp.mean(((out - prev_out) - (target - prev_target)) ** 2)
    return spatial + 0.7 * jnp.where(has_prev, temporal, 0.0) + 0.3 * jnp.mean(frame.depth * out)


def _loop(p, carry, frames, targets, loss_frames, keep_at=None):
    """``window_loss`` written out frame by frame: returns (loss, (last, kept))."""
    n = frames.color.shape[0]
    state, prev_out, prev_target, has_prev = carry
    total, kept = 0.0, None
    for t in range(n):
        frame = seqdata.at(frames, t)
        out, state = _step(p, state, frame)
        if t >= n - loss_frames:
            total = total + _loss(out, targets[t], prev_out, prev_target, has_prev, frame)
        prev_out, prev_target = out.astype(jnp.float32), targets[t].astype(jnp.float32)
        has_prev = jnp.asarray(True)
        if t + 1 == keep_at:
            kept = rollout.Carry(state, prev_out, prev_target, has_prev)
    return total / loss_frames, (rollout.Carry(state, prev_out, prev_target, has_prev), kept)


def _carry_in(frames, targets, has_prev):
    """A carry as one in the middle of a video (nonzero previous output and target)."""
    rng = np.random.default_rng(7)
    return rollout.Carry(_init_state(seqdata.at(frames, 0)) + 0.05,
                         jnp.asarray(rng.uniform(0.1, 0.9, targets.shape[1:]), jnp.float32),
                         jnp.asarray(rng.uniform(0.1, 0.9, targets.shape[1:]), jnp.float32),
                         jnp.asarray(has_prev))


def _close(a, b, rtol=1e-12, atol=1e-14):
    """Equal trees, leaf by leaf with equal dtypes; float32 leaves (the carried previous
    frame and its gradients) to 2 ulp, since a float64 difference in the last bits can
    round either way."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert x.dtype == y.dtype, (x.dtype, y.dtype)
        if x.dtype == jnp.bool_:
            np.testing.assert_array_equal(x, y)
        elif x.dtype == jnp.float32:
            np.testing.assert_allclose(x, y, rtol=max(rtol, 2.4e-7), atol=atol)
        else:
            np.testing.assert_allclose(x, y, rtol=rtol, atol=atol)


def test_start_is_an_empty_float32_carry():
    target = jnp.ones((B, H, W, 3), jnp.float16)
    c = rollout.start("state", target)
    assert c.state == "state" and not bool(c.has_prev)
    for buf in (c.prev_out, c.prev_target):
        assert buf.shape == target.shape and buf.dtype == jnp.float32
        np.testing.assert_array_equal(buf, 0.0)
    assert c.prev_out is not c.prev_target  # two buffers: the carry may be donated


def test_first_state_reads_the_first_frame(x64):
    frames, _ = _frames()
    np.testing.assert_array_equal(rollout.first_state(_model(False), frames),
                                  _init_state(seqdata.at(frames, 0)))


def test_parts_of_a_model_with_and_without_the_split():
    assert rollout.parts(_model(True)) == (_advance, _prepare)
    plain = _model(False)
    assert rollout.parts(plain) == (_step, None)


@pytest.mark.parametrize("kw", [{}, {"remat": True}, {"remat": "dots"},
                                {"remat": "dots_no_batch"}, {"unroll": 2}, {"unroll": True}])
def test_outputs_equal_the_loop(x64, kw):
    frames, _ = _frames()
    p, s0 = _params(), _init_state(seqdata.at(frames, 0))
    outs, last = rollout.outputs(_step, p, s0, frames, **kw)
    s, want = s0, []
    for t in range(T):
        o, s = _step(p, s, seqdata.at(frames, t))
        want.append(o)
    # compiled scan against the loop op by op: XLA may fuse differently (1 ulp seen)
    _close((outs, last), (jnp.stack(want), s), rtol=1e-14, atol=1e-15)


def test_outputs_check_inputs_at_the_boundary_only(x64):
    frames, _ = _frames()
    p, s0 = _params(), _init_state(seqdata.at(frames, 0))
    bad = frames._replace(depth=frames.depth.at[4, 1, 0, 2, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="depth"):
        rollout.outputs(_step, p, s0, bad)
    outs, _ = rollout.outputs(_step, p, s0, bad, check=False)  # asked not to check
    assert not np.isfinite(np.asarray(outs[4, 1])).all()
    # inside a trace the check is skipped (it needs concrete values), not an error
    jitted, _ = jax.jit(lambda f: rollout.outputs(_step, p, s0, f))(frames)
    _close(jitted, rollout.outputs(_step, p, s0, frames)[0], rtol=1e-14, atol=1e-15)
    with pytest.raises(ValueError, match="remat: expected True, False or one of"):
        rollout.outputs(_step, p, s0, frames, remat="everything")


def test_video_runs_from_the_first_state(x64):
    frames, _ = _frames()
    model, p = _model(True), _params()
    got = rollout.video(model, p, frames)
    want, _ = rollout.outputs(_step, p, _init_state(seqdata.at(frames, 0)), frames)
    _close(got, want, rtol=1e-14, atol=1e-15)
    with pytest.raises(ValueError, match="color"):
        rollout.video(model, p, frames._replace(color=frames.color.at[1].set(jnp.nan)))


@pytest.mark.parametrize("unroll", [1, 3])
def test_metrics_see_the_previous_frame_and_keep_no_outputs(x64, unroll):
    frames, targets = _frames()
    p, s0 = _params(), _init_state(seqdata.at(frames, 0))

    def metric(out, target, prev_out, prev_target, has_prev, frame):
        return {"err": jnp.mean(jnp.abs(out - target), axis=(1, 2, 3)),
                "prev": (jnp.mean(prev_out), jnp.mean(prev_target),
                         jnp.asarray(prev_out.dtype == jnp.float32), has_prev),
                "depth": jnp.mean(frame.depth)}

    ms, last = rollout.metrics(_step, p, s0, frames, targets, metric, unroll=unroll)
    s, prev_out, prev_target, has_prev, want = s0, jnp.zeros((B, H, W, 3), jnp.float32), \
        jnp.zeros((B, H, W, 3), jnp.float32), False, []
    for t in range(T):
        o, s = _step(p, s, seqdata.at(frames, t))
        want.append(metric(o, targets[t], prev_out, prev_target, jnp.asarray(has_prev),
                           seqdata.at(frames, t)))
        prev_out, prev_target, has_prev = o.astype(jnp.float32), targets[t].astype(
            jnp.float32), True
    want = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *want)
    _close((ms, last), (want, s), rtol=1e-14, atol=1e-15)
    assert not bool(ms["prev"][3][0]) and bool(ms["prev"][3][1:].all())
    assert bool(ms["prev"][2].all())
    with pytest.raises(ValueError, match="motion"):
        rollout.metrics(_step, p, s0, frames._replace(motion=frames.motion[..., :1]),
                        targets, metric)


# (mode, loss_frames, keep_at). Windows: the loss on the last frame, on a middle span,
# on all of it; no cut, a cut inside the loss-free part, inside the loss frames, at the
# end. Every window with the plain scan; each other mode (which changes how a segment
# is scanned, not how the window is cut) with the windows that reach its branches.
ALL_WINDOWS = [(1, None), (2, 1), (3, 4), (T, 3), (4, T)]
CASES = ([({}, *w) for w in ALL_WINDOWS]
         + [({"remat": True}, T, 3), ({"remat": "dots"}, T, 3), ({"unroll": 2}, T, 3)]
         + [({"remat": "reverse"}, *w) for w in ((2, 1), (T, 3), (4, T))]
         + [({"prepare": True}, 3, 4), ({"prepare": True}, T, 3),
            ({"prepare": True, "remat": "reverse"}, T, 3)])


@functools.lru_cache(maxsize=None)
def _reference_vg(loss_frames, keep_at):
    """The loop's loss, carries and gradients (jitted once per window, shared by the
    modes)."""
    frames, targets = _frames(first=False)
    c0 = _carry_in(frames, targets, loss_frames == T)

    def f(p, state, prev_out, prev_target):
        return _loop(p, rollout.Carry(state, prev_out, prev_target, c0.has_prev), frames,
                     targets, loss_frames, keep_at)

    return jax.jit(jax.value_and_grad(f, argnums=(0, 1, 2, 3), has_aux=True))(
        _params(), c0.state, c0.prev_out, c0.prev_target)


@pytest.mark.parametrize("mode,loss_frames,keep_at", CASES,
                         ids=lambda v: "-".join(f"{k}={x}" for k, x in v.items()) or "plain"
                         if isinstance(v, dict) else str(v))
def test_window_loss_equals_the_loop_with_gradients(x64, mode, loss_frames, keep_at):
    """Loss, final and kept carries, and gradients with respect to the parameters and
    to every differentiable part of the incoming carry, against ``_loop`` (float64,
    1e-12); the incoming carry has a previous frame (``has_prev``) when the loss covers
    the whole window, so its first frame has a temporal term."""
    frames, targets = _frames(first=False)
    has_prev = loss_frames == T  # a temporal term on the window's first frame
    c0 = _carry_in(frames, targets, has_prev)
    mode = dict(mode)
    step = _step
    if mode.pop("prepare", False):
        step, mode["prepare"] = _advance, _prepare

    def got(p, state, prev_out, prev_target):
        return rollout.window_loss(step, _loss, p,
                                   rollout.Carry(state, prev_out, prev_target, c0.has_prev),
                                   frames, targets, loss_frames=loss_frames, keep_at=keep_at,
                                   **mode)

    (l1, (last1, kept1)), g1 = jax.jit(jax.value_and_grad(got, argnums=(0, 1, 2, 3),
                                                          has_aux=True))(
        _params(), c0.state, c0.prev_out, c0.prev_target)
    (l0, (last0, kept0)), g0 = _reference_vg(loss_frames, keep_at)
    np.testing.assert_allclose(l1, l0, rtol=1e-12)
    assert (kept1 is None) == (keep_at is None)
    _close((last1, kept1, g1), (last0, kept0, g0))
    assert bool(last1.has_prev)
    # every part of the gradient is exercised: parameters, state, previous frame
    assert all(float(jnp.abs(x).max()) > 1e-6 for x in jax.tree_util.tree_leaves(g0[:2]))
    if has_prev:
        assert float(jnp.abs(g0[2]).max()) > 1e-6 and float(jnp.abs(g0[3]).max()) > 1e-6


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_reverse_backward_gives_the_frames_zero_cotangents_of_their_type(x64, dtype):
    """``remat="reverse"`` differentiates the parameters and the carry (above); the
    frames are data, and its backward hands them zero cotangents in their own types
    (float64 or float32 with 64-bit types on; autodiff's would be the frames' true
    gradients), the reset flags float0 as autodiff does. (A floating test that is
    ``issubdtype(x, None)``, i.e. float64 only, passed the float64 case alone.)"""
    frames, targets = _frames(first=False)
    c0 = _carry_in(frames, targets, True)  # float64 state: the parameters are float64
    frames = jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, frames)

    def back(mode):
        def f(c, fr):
            return rollout.window_loss(_step, _loss, _params(), c, fr, targets,
                                       loss_frames=T, **mode)[0]
        loss, vjp = jax.vjp(f, c0, frames)
        return vjp(jnp.ones_like(loss))

    (c_ad, f_ad), (c_rev, f_rev) = back({}), back({"remat": "reverse"})
    assert c_ad.has_prev.dtype == c_rev.has_prev.dtype == jax.dtypes.float0
    leaves_ad, leaves_rev = jax.tree_util.tree_leaves(f_ad), jax.tree_util.tree_leaves(f_rev)
    assert [(x.dtype, x.shape) for x in leaves_rev] == [(x.dtype, x.shape) for x in leaves_ad]
    assert jax.dtypes.float0 in [x.dtype for x in leaves_rev]            # the reset flags
    assert dtype in [x.dtype for x in leaves_rev]
    assert not any(np.any(np.asarray(x, bool)) for x in leaves_rev
                   if x.dtype != jax.dtypes.float0)


@pytest.mark.parametrize("mode", [{}, {"remat": "reverse"}], ids=["plain", "reverse"])
def test_float32_window_loss_stays_float32_with_64_bit_types_on(mode):
    """A float32 window (frames, parameters, carry: float32 training) gives a float32
    loss with 64-bit types on, in both backward modes: the loss-free frames before the
    loss frames add float32 zeros, not default-typed ones."""
    frames, targets = _frames(first=False)                      # float32: x64 is off
    params, c0 = _params(), _carry_in(frames, targets, False)
    assert frames.color.dtype == params["a"].dtype == jnp.float32
    with jax.enable_x64(True):
        loss, _ = rollout.window_loss(_step, _loss, params, c0, frames, targets,
                                      loss_frames=2, **mode)
    assert loss.dtype == jnp.float32


def test_loss_ops_carry_the_profilers_stage_name():
    """``jtus.profile`` attributes a training step's ops to stages by their scope names
    (``profile.TRAINING_STAGES``): the window loss's ops are in the ``loss`` scope, the hoisted
    preparation's in ``prepare``."""
    from jtus import profile

    frames, targets = _frames(first=False)
    c0 = _carry_in(frames, targets, False)
    hlo = jax.jit(lambda p: rollout.window_loss(_advance, _loss, p, c0, frames, targets,
                                                loss_frames=2, prepare=_prepare)[0]).lower(
        _params()).as_text(debug_info=True)
    assert "loss" in profile.TRAINING_STAGES
    names = set(re.findall(r'loc\("([^"]+)"', hlo))    # the ops' scoped names
    assert any(n.split("/")[0] == "loss" or "/loss/" in n for n in names)
    assert any("/prepare/" in n for n in names)


def test_window_loss_rejects_bad_windows():
    frames, targets = _frames()
    c0 = _carry_in(frames, targets, False)
    p = _params()

    def call(**kw):
        kw = {"loss_frames": 1} | kw
        return rollout.window_loss(_step, _loss, p, c0, frames, targets, **kw)

    for lf in (0, T + 1):
        with pytest.raises(ValueError, match=rf"loss_frames: expected 1..{T} \(the window "
                                             rf"length\), got {lf}"):
            call(loss_frames=lf)
    for k in (0, T + 1):
        with pytest.raises(ValueError, match=rf"keep_at: expected 1..{T}, got {k}"):
            call(keep_at=k)
    with pytest.raises(ValueError, match="unroll: remat='reverse' scans one frame"):
        call(remat="reverse", unroll=2)
    with pytest.raises(ValueError, match="remat: expected"):
        call(remat="everything")
    # the edges are accepted
    assert np.isfinite(float(call(loss_frames=T, keep_at=T)[0]))
    assert np.isfinite(float(call(keep_at=1, remat="reverse", unroll=1)[0]))


def test_tbptt_windows_plan_edges():
    assert rollout.tbptt_windows(5, 5, 5) == [(0, 5)]
    assert rollout.tbptt_windows(5, 1, 1) == [(t, t + 1) for t in range(5)]
    assert rollout.tbptt_windows(7, 2, 3) == [(0, 3), (2, 5), (4, 7)]
    # (length - k2) a multiple of k1 while (length + k2) is not: the difference is checked
    assert rollout.tbptt_windows(7, 3, 4) == [(0, 4), (3, 7)]
    w = rollout.tbptt_windows(6, 3, 3)[1]
    assert (w.start, w.stop) == (3, 6)
    for k1, k2, length in ((0, 2, 4), (2, 5, 4), (3, 2, 4)):
        with pytest.raises(ValueError, match=rf"tbptt: expected 1 <= k1 <= k2 <= sequence "
                                             rf"length, got k1={k1}, k2={k2}, length={length}"):
            rollout.tbptt_windows(length, k1, k2)
    with pytest.raises(ValueError, match=r"\(length - k2\) = 3 must be a multiple of k1 = 2"):
        rollout.tbptt_windows(7, 2, 4)


@pytest.mark.parametrize("k1,k2", [(2, 4), (4, 4), (2, 2), (1, 6)])
def test_tbptt_grads_chain_windows_like_the_loop(x64, k1, k2):
    """Each window's loss and gradients at fixed parameters, and the carry handed to
    the next window (the one after its first k1 frames, without gradient), against the
    loop; the returned carry is the one the next window would start from."""
    frames, targets = _frames(T=8, reset_at=((5, 0),))
    p = _params()
    c = rollout.start(_init_state(seqdata.at(frames, 0)), targets[0])
    results, last = seqdata.tbptt_grads(_step, _loss, p, c, frames, targets, k1=k1, k2=k2)
    windows = rollout.tbptt_windows(8, k1, k2)
    assert len(results) == len(windows)
    for (loss, grads), w in zip(results, windows):
        fr, tg = jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (frames, targets))
        keep = k1 if k1 < k2 else None
        (l0, (end, kept)), g0 = jax.value_and_grad(
            lambda q: _loop(q, c, fr, tg, k1, keep), has_aux=True)(p)
        np.testing.assert_allclose(loss, l0, rtol=1e-12)
        _close(grads, g0)
        c = kept if kept is not None else end
    _close(last, c)
    # the next window would start at frame 8 - k2 + k1: its state is the loop's there
    outs, _ = rollout.outputs(_step, p, _init_state(seqdata.at(frames, 0)), frames)
    np.testing.assert_allclose(last.prev_out, outs[8 - k2 + k1 - 1].astype(jnp.float32),
                               rtol=2.4e-7, atol=0)
